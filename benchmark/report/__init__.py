"""The run report: ``python -m benchmark report RUN_DIR`` (see :mod:`benchmark.report.build`)."""

from benchmark.report.build import DEFAULT_SEQUENCES, build_report

__all__ = ["DEFAULT_SEQUENCES", "build_report"]
