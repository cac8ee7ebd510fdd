"""Reading a design spec: a YAML file validated by its family's model before any CAD work.

The ``family`` key (default ``chic``) picks the model from the registry
:data:`chic_design.families.FAMILIES`. Unknown keys, wrong types,
out-of-range and contradictory values are rejected by :func:`load_spec` with
a one-line :class:`~chic_design.errors.SpecError` naming the file, the key
path and what is allowed. ``chic-design schema`` prints :func:`json_schema`.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from pydantic import BaseModel, ValidationError

from chic_design.errors import SpecError
from chic_design.families import DEFAULT_FAMILY, family_named
from chic_design.families.sections import DesignSpec
from chic_register.errors import InputFileError
from chic_register.model.geometry import FORMAT as GEOMETRY_FORMAT
from chic_register.util.safeload import MAX_YAML_BYTES, load_yaml_file, read_regular_file


def json_schema(family: str = DEFAULT_FAMILY) -> dict:
    """JSON Schema of the spec of ``family`` (for editors)."""
    fam = family_named(family)
    schema = fam.spec_model.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = f"{fam.title} design spec"
    return schema


def format_validation_error(path: Path, err: dict, root: type[BaseModel],
                            schema_hint: str = "see `chic-design schema`") -> str:
    """One line for a pydantic error in a YAML file of model ``root``: the file, the key path, what is wrong and what was given."""
    loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
    msg = err["msg"].removeprefix("Value error, ")
    kind = err["type"]
    if kind == "extra_forbidden":
        model = root
        for part in err["loc"][:-1]:
            field = model.model_fields.get(str(part))
            model = field.annotation if field is not None else None
            if not isinstance(model, type) or not issubclass(model, BaseModel):
                model = None
                break
        allowed = ", ".join(model.model_fields) if model is not None else schema_hint
        return f"{path}: unknown key '{loc}'; allowed keys here: {allowed}"
    if kind == "missing":
        return f"{path}: missing key '{loc}'"
    shown = err.get("input")
    if isinstance(shown, (dict, list)) or kind.startswith("value_error"):
        return f"{path}: {loc}: {msg}"
    shown = repr(shown)
    return f"{path}: {loc}: {msg} (got {shown if len(shown) <= 60 else shown[:57] + '...'})"


def parse_spec(data, path="<spec>") -> DesignSpec:
    """Validate parsed YAML ``data`` into its family's spec model; raises :class:`SpecError`."""
    path = Path(path)
    if not isinstance(data, dict):
        raise SpecError(f"{path}: the spec must be a YAML mapping of keys, got {type(data).__name__}")
    if data.get("format") == GEOMETRY_FORMAT:
        raise SpecError(f"{path}: this is a geometry file (chic-design build writes it), not a design spec; "
                        "give a spec such as designs/neuro.yaml")
    model = family_named(data.get("family", DEFAULT_FAMILY), f"{path}: family").spec_model
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise SpecError(format_validation_error(path, exc.errors()[0], model)) from None


def load_spec(path) -> DesignSpec:
    """Read and validate a spec file; raises :class:`SpecError` with a one-line message."""
    path = Path(path)
    try:
        data = load_yaml_file(path, "spec file")
    except InputFileError as exc:
        raise SpecError(str(exc)) from None
    return parse_spec(data, path)


def spec_sha256(path) -> str:
    """SHA-256 of the spec file's bytes (recorded in the geometry file's ``source``)."""
    try:
        return hashlib.sha256(read_regular_file(path, "spec file", MAX_YAML_BYTES)).hexdigest()
    except InputFileError as exc:
        raise SpecError(str(exc)) from None
