"""``describe``: a prior's architecture and parameter counts, or a body model."""

from __future__ import annotations

from benchmark.commands.common import HelpFormatter

from benchmark.run.registry import make_adapter


def _count(module) -> tuple[int, int]:
    params = list(module.parameters())
    return sum(p.numel() for p in params), sum(p.numel() for p in params if p.requires_grad)


def parameter_rows(module) -> list[tuple[str, int, int]]:
    """(name, parameters, trainable) per top-level child of ``module``. An adapter whose parameters
    all sit in one child (``VPoserSlerp.vposer``) is looked through, so the rows name the
    network's own parts (``vposer.encoder_net``, ``vposer.decoder_net``) for every size."""
    children = [(n, c) for n, c in module.named_children() if _count(c)[0] > 0]
    prefix = ""
    while len(children) == 1 and _count(children[0][1])[0] == _count(module)[0] and list(children[0][1].children()):
        name, module = children[0]
        prefix += name + "."
        children = [(n, c) for n, c in module.named_children() if _count(c)[0] > 0]
    rows = [(prefix + n, *_count(c)) for n, c in children]
    direct = sum(p.numel() for p in module.parameters(recurse=False))
    if direct:
        rows.append((prefix + "(own parameters)", direct, sum(p.numel() for p in module.parameters(recurse=False) if p.requires_grad)))
    return rows


def _print_counts(module, note: str = "") -> None:
    total, trainable = _count(module)
    print(f"parameters: {total:,} (trainable {trainable:,}{note})")
    rows = parameter_rows(module)
    width = max((len(r[0]) for r in rows), default=0)
    for name, n, t in rows:
        print(f"  {name.ljust(width)}  {n:>12,}  (trainable {t:,})")


def describe_body(spec: str) -> str:
    """A body model in a few lines: kind, file, vertices, faces, joints, shape parameters."""
    from benchmark.body import get_body

    body = get_body(spec)
    source = getattr(body, "source_path", None)
    file_joints = getattr(body, "num_file_joints", None)
    lines = [f"body {body.name}" + (f" from {source}" if source else " (embedded)"),
             f"  vertices {body.num_vertices:,}, faces {int(body.faces.shape[0]):,}, joints driven 22"
             + (f" (file: {file_joints})" if file_joints else "") + f", shape parameters {body.shape_dim}"]
    return "\n".join(lines)


def _cmd_describe(args) -> int:
    from benchmark.run.registry import get_prior_class

    if args.body:
        print(describe_body(args.body))
        if args.name is None:
            return 0
    elif args.name is None:
        raise ValueError("describe needs a prior NAME (python -m benchmark list priors) or --body KIND")
    cls = get_prior_class(args.name)
    from priors.base import PaperNetwork

    if args.size == "paper" and args.weights is None and isinstance(cls, type) and issubclass(cls, PaperNetwork):
        net = cls.paper_network()
        print(f"{args.name} (paper size, random weights: architecture only, no checkpoint loaded)")
        print(net)
        _print_counts(net)
        return 0
    adapter = make_adapter(args.name, size=args.size, weights=args.weights, device="cpu")
    print(adapter.describe())
    frozen = "; the adapter freezes its network" if _count(adapter)[0] and not _count(adapter)[1] else ""
    _print_counts(adapter, frozen)
    return 0


def add_command(sub) -> None:
    from benchmark.core import argtypes as at

    fmt = HelpFormatter
    p = sub.add_parser("describe", help="architecture summary and parameter counts of a prior (--size paper without --weights: "
                       "the paper-size network with random weights)", formatter_class=fmt)
    p.add_argument("name", nargs="?", default=None, help="a prior (python -m benchmark list priors)")
    p.add_argument("--size", choices=["embedded", "paper"], default="embedded")
    p.add_argument("--weights", action=at.Once, default=None)
    p.add_argument("--body", default=None, help="also describe a body model: anny | smpl | smplh | smplx[=PATH[:gender]]")
    p.set_defaults(func=_cmd_describe)
