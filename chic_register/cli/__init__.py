"""The chic-register command line: main assembles one module per subcommand.

solve, precision, simulate, evaluate, reslice and track each hold their
add_parser(subparsers) and run(args); inputs holds the flags and input checks
several commands share, console where messages go, exits how a failure ends.
"""
