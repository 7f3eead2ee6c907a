"""The priors the benchmark ships, each registered by name through the ``benchmark.priors`` entry points.

:mod:`priors.base` is the prior contract (:class:`~priors.base.PriorAdapter` and the optional
interfaces it may combine with: ``MotionEncoder``, ``MotionDenoiser``, ``AnchorDecoder``,
``Trainable``, ``ExportableDecoder``, ``PaperNetwork``, ``InterpolationBaseline``);
:mod:`priors.checkpoints` the one checkpoint API (``CheckpointReport``, the strict state-dict
loader ``load_state_strict``) every ``checkpoint.py`` builds on; :mod:`priors.training`
holds what every embedded training recipe shares (data windows, the loop, checkpoint and record
writing, the recipe command line). The baselines are single modules (:mod:`priors.no_prior`,
:mod:`priors.slerp`). Every learned prior is a package with the same files, each with one job::

    priors/<name>/
        __init__.py     the method in its docstring; exports the adapter
        model.py        the networks at any size (paper and embedded), pure torch, no I/O
        checkpoint.py   load(path, size) -> (network, CheckpointReport): official and embedded formats, strict
        adapter.py      the PriorAdapter (and the module it exports to ONNX)
        train.py        the embedded training recipe (``python -m priors.<name>.train``)

(:mod:`priors.hmvae` adds ``skeleton.py`` and ``trajectory.py``, :mod:`priors.structured_latent`
``representation.py`` and ``gradnorm.py``.) Imports go one way: model <- checkpoint <- adapter, and
train imports model and checkpoint; an adapter imports its train module only inside
``train_embedded``. Rotation and heading-frame helpers that more than one prior needs live in
:mod:`benchmark.core.frames` and :mod:`benchmark.core.rotations`.
"""
