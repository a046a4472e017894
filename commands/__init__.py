"""lampsam.commands: the CLI's subcommands, one module per command family (the CLI's layer:
it may import any stage; no stage imports it). :mod:`lampsam.cli` builds the parser from
their ``add_*`` functions.

Modules:

* :mod:`~lampsam.commands._args` -- argument types and options shared by the commands.
* :mod:`~lampsam.commands.ceiling` -- ``simulate``, ``demo``, ``compare``, ``batch``.
* :mod:`~lampsam.commands.slam` -- ``slam`` (logged runs, text logs, MRCLAM, ceiling maps).
* :mod:`~lampsam.commands.stereo` -- ``stereo-sim``, ``stereo``, ``stereo-experiment``.
* :mod:`~lampsam.commands.localization` -- ``kinect-sim``, ``build-map``, ``show-map``, ``localize``, ``table1``.
* :mod:`~lampsam.commands.photos` -- ``frontend-eval``, ``gallery``.
* :mod:`~lampsam.commands.bags` -- ``import-bag``, ``export-bag``.
"""
