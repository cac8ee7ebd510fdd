"""The ``chic-design`` command line: :mod:`.main` and one module per subcommand, a thin layer over the library."""
