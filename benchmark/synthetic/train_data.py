"""The embedded priors' training data, as the `train` command and the recipes' command lines hand it
to a prior's training recipe (a prior imports only the core layer and never builds data itself:
docs/architecture.md, "Packages and layers")."""

from __future__ import annotations


class SyntheticTrainingData:
    """The project's synthetic splits and what recipes read off them: ``split("train")`` /
    ``split("val")`` (:func:`benchmark.synthetic.splits.build_split`, cached on disk), ``source(name)``
    (where a split comes from, for the training record) and ``find_cycles(motion, **options)`` (its
    motion cycles, :func:`benchmark.synthetic.cycles.find_cycles`, for the structured latent space)."""

    def split(self, name: str) -> list:
        from benchmark.synthetic.splits import build_split

        return build_split(name)

    def source(self, name: str) -> str:
        return f"benchmark.synthetic.splits.build_split({name!r})"

    def find_cycles(self, motion, **options) -> list:
        from benchmark.synthetic.cycles import find_cycles

        return find_cycles(motion, **options)
