"""``chic-design schema``: the JSON Schema of a family's design spec, for editors."""

from __future__ import annotations

import json

from chic_design.families import DEFAULT_FAMILY, FAMILIES
from chic_design.spec import json_schema


def add_parser(subparsers):
    s = subparsers.add_parser("schema", help="print the spec's JSON Schema")
    s.add_argument("--family", default=DEFAULT_FAMILY, choices=list(FAMILIES),
                   help=f"which spec family's schema (default {DEFAULT_FAMILY})")
    return s


def run(args) -> int:
    print(json.dumps(json_schema(args.family), indent=2))
    return 0
