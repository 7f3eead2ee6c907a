"""The command line: one module per command of ``python -m benchmark`` (the commands layer).

Each module has ``add_command(sub)``, which adds its parser (every ``add_parser`` of the project
is here) and binds the function that runs it; :func:`benchmark.cli.build_parser` calls them in the
order of ``--help``. A command module checks what a user can get
wrong and calls library code of the lower layers (``benchmark.run``, ``benchmark.tools``,
``benchmark.report``...); nothing imports a command module except :mod:`benchmark.cli`, another
command or the tests. :mod:`.common` holds what several commands share (``resolve_device``).
"""
