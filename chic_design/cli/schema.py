"""``chic-design schema``: the JSON Schema of a family's design spec, for editors."""

from __future__ import annotations

import json


def add_parser(subparsers):
    s = subparsers.add_parser("schema", help="print the spec's JSON Schema")
    s.add_argument("--family", metavar="NAME",
                   help="which spec family's schema (default: chic; an unknown name lists the families)")
    return s


def run(args) -> int:
    from chic_design.families import DEFAULT_FAMILY, family_named  # the families load here: --help starts fast
    from chic_design.spec import json_schema

    family = family_named(DEFAULT_FAMILY if args.family is None else args.family, "--family")
    print(json.dumps(json_schema(family.name), indent=2))
    return 0
