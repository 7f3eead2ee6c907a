"""The data layer: observations synthesised from motions, their degradation, the arrays a unit
keeps, a table's test motions (``benchmark.loaders`` and ``benchmark.synthetic`` are data too).
Imports the core and the data."""
