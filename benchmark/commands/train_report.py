"""``train-report``: the training and validation curves of the embedded priors
(:mod:`benchmark.tools.train_report`)."""

from __future__ import annotations

from benchmark.commands.common import HelpFormatter


def _cmd_train_report(args) -> int:
    from benchmark.tools.train_report import build_train_report

    build_train_report(args.weights_dir, args.out)
    return 0


def add_command(sub) -> None:
    from priors.training import WEIGHTS_DIR

    p = sub.add_parser("train-report", help="training and validation curves of the embedded priors (from their records)",
                       formatter_class=HelpFormatter)
    p.add_argument("--weights-dir", default=str(WEIGHTS_DIR), help="folder of the weights and their NAME.json records")
    p.add_argument("--out", default="runs/train-report")
    p.set_defaults(func=_cmd_train_report)
