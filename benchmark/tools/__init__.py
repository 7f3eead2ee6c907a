"""Library code behind some commands, in the run layer: one capture's completion (``complete``),
speed measurements (``perf``), the prior conformance kit (``conformance``), ONNX export
(``export_onnx``), table comparison (``compare``), the fit check (``fit_check``), the completion
error breakdown (``error_breakdown``), the training report (``train_report``). Their command lines
live in :mod:`benchmark.commands`."""
