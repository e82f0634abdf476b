"""The ``packml`` command line: ``packml <verb> --help`` for each verb."""
