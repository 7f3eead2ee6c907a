"""The core layer: conventions (skeleton, rotations, frames), the Motion type, interpolation,
input checks and the small utilities every layer shares (safe loading, argument types, signals,
output folders, provenance, fit diagnostics, the work unit and its result). Imports only the core
(``benchmark.body`` and ``benchmark.metrics`` are core too)."""
