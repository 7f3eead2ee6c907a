"""``train``: train a prior's embedded weights on the synthetic training split (the recipe of its
:class:`priors.base.Trainable`; the data handed over as ``dataset``)."""

from __future__ import annotations

from pathlib import Path

from benchmark.commands.common import HelpFormatter


def _cmd_train(args) -> int:
    from benchmark.run.registry import get_prior_class

    from benchmark.core.outdir import check_out_dir

    cls = get_prior_class(args.name)
    from priors.base import Trainable

    if not (isinstance(cls, type) and issubclass(cls, Trainable)):
        raise ValueError(f"prior {args.name!r} has no training recipe (it is not a priors.base.Trainable: "
                         "no train_embedded classmethod)")
    out = Path(args.out) if args.out is not None else None
    from benchmark.synthetic.train_data import SyntheticTrainingData
    from priors.training import WEIGHTS_DIR
    from priors.training_state import saved_states, training_session

    # the weights folder first: a wrong --out fails in a second, not after hours of training
    check_out_dir(out if out is not None else WEIGHTS_DIR, min_free_bytes=1 << 20,
                  what="--out" if out is not None else "the weights folder")

    # every loop of the recipe checkpoints here; --resume continues from it (priors/training_state.py)
    state_dir = (out or WEIGHTS_DIR) / ".train_state" / args.name
    states = saved_states(state_dir)
    if args.resume and not states:
        raise FileNotFoundError(f"train {args.name} --resume: no training state in {state_dir}; start the training "
                                f"without --resume (it checkpoints every {args.checkpoint_every} steps)")
    if states and not args.resume:
        # hours of training are not thrown away because --resume was forgotten
        if not args.force:
            raise FileExistsError(f"{state_dir} holds the state of an earlier training of {args.name} "
                                  f"({', '.join(p.name for p in states)}): pass --resume to continue it, or --force to "
                                  "start over (the state is replaced)")
        for p in states:  # starting over: no loop may later be replayed from the earlier run
            p.unlink()
    try:
        with training_session(state_dir, resume=args.resume, checkpoint_every=args.checkpoint_every,
                              val_every=args.val_every):
            # the training data: the synthetic splits, handed to the recipe (priors never build data)
            record = cls.train_embedded(out_dir=out, steps=args.steps, seed=args.seed, overwrite=args.force,
                                        dataset=SyntheticTrainingData())
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: say what is kept and how to go on
        import sys

        kept = saved_states(state_dir)
        again = f"python -m benchmark train {args.name}" + "".join(
            f" {flag} {value}" for flag, value in (("--steps", args.steps), ("--seed", args.seed), ("--out", args.out))
            if value is not None)
        print(f"train {args.name}: the training state is kept in {state_dir} ({', '.join(p.name for p in kept)}); "
              f"`{again} --resume` continues it" if kept else
              f"train {args.name}: stopped before its first checkpoint (every {args.checkpoint_every} steps); nothing "
              "to resume", file=sys.stderr)
        raise
    print(record)
    return 0


def add_command(sub) -> None:
    from benchmark.core import argtypes as at

    fmt = HelpFormatter
    p = sub.add_parser("train", help="train a prior's embedded weights on the synthetic training split", formatter_class=fmt)
    p.add_argument("name")
    p.add_argument("--steps", type=at.positive_int, default=None, help="training steps (default: the recipe's)")
    p.add_argument("--seed", type=at.seed, default=0)
    p.add_argument("--out", default=None, help="output folder (default: priors/weights)")
    p.add_argument("--force", action="store_true",
                   help="overwrite existing weights and records, and start over from an earlier training's state")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted training from its last checkpoint (OUT/.train_state/NAME; add --force when "
                        "the weights file exists)")
    p.add_argument("--checkpoint-every", type=at.positive_int, default=200,
                   help="save the resumable training state every N steps")
    p.add_argument("--val-every", type=at.non_negative_int, default=500,
                   help="log the validation loss every N steps (0: at the end only)")
    p.set_defaults(func=_cmd_train)
