"""What several commands share: the help formatter, the ``--device`` check, ``NAME=VALUE`` options."""

from __future__ import annotations

import argparse


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` with each option's default, added only where its help text does not state the
    default itself (``default: full on CUDA, quick on CPU``), so that no option shows two defaults
    (``... (default: the CPU cores) (default: None)``)."""

    def _get_help_string(self, action):
        help_text = action.help or ""
        if "default" in help_text.lower():
            return help_text
        return super()._get_help_string(action)


def resolve_device(name: str | None) -> str:
    """The device to run on: ``None`` picks cuda when available; otherwise ``cpu``, ``cuda`` or
    ``cuda:N``, checked here so that a wrong name fails before any work."""
    import torch

    if name is None:
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError, TypeError):
        raise ValueError(f"--device {name!r}: not a device name; use cpu, cuda or cuda:N") from None
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"--device {name!r}: the harness runs on cpu or cuda (cuda:N), not {dev.type!r}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"--device {name}: no CUDA device is available on this machine "
                             "(torch.cuda.is_available() is False); use --device cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA device(s) "
                             f"(cuda:0..cuda:{torch.cuda.device_count() - 1})")
    return name


def parse_pairs(items, what: str) -> dict:
    """``["NAME=VALUE", ...]`` (a repeatable option ``what``) -> {NAME: VALUE}; a malformed or
    repeated NAME is an error naming the option."""
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key or not value:
            raise ValueError(f"{what} must look like NAME=VALUE, got {item!r}")
        if key in out:
            raise ValueError(f"{what}: {key!r} is given twice ({key}={out[key]} and {item}); give each NAME once")
        out[key] = value
    return out
