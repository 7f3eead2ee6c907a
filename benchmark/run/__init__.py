"""The run layer: running a table (``table_run``), the runner and its backends, derivation,
writing, the prior registry, the catalog of specs and profiles (``benchmark.report`` and
``benchmark.tools`` are run too). Imports every layer but the commands."""
