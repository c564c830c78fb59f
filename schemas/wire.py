"""Field specifications and the msgpack codec that every wire message derives from.

A message type is a frozen dataclass whose fields carry a :class:`Spec` in their metadata (see
:func:`spec`). From that one definition this module derives encoding, decoding with full validation,
and (in :mod:`schemas.jsonschema`) the JSON Schema documents, so the three can never disagree.

Wire form: a msgpack map ``{"type": <name>, "v": <version>, <field>: <value>, ...}``. A NumPy array
travels as a map ``{"dtype": "<f4", "shape": [B], "data": <bin>}``: little-endian, C order, raw bytes,
never a list of floats.

Every decoding failure raises :class:`MessageError` (a :class:`schemas.errors.FormatError`) whose
``reason`` is one of :data:`REASONS`, so receivers can count rejections by kind.
"""

from __future__ import annotations

import abc
import dataclasses
import hashlib
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import msgpack
import numpy as np

from schemas.errors import FormatError

#: every value of :attr:`MessageError.reason`
REASONS = (
    "malformed",  # not msgpack, not a map, or no type/version header
    "type",  # unknown message type, or a type not expected on this key
    "version",  # a version of a known type this build does not read
    "missing_field",  # a required field is absent
    "unknown_field",  # a field the type does not define
    "field_type",  # a field holds the wrong kind of value (text for a number, ...)
    "dtype",  # an array has another dtype than its spec
    "shape",  # an array has the wrong number of dimensions or a wrong/inconsistent length
    "size",  # an array's byte count does not match dtype and shape
    "nonfinite",  # NaN or infinity where only finite values are allowed
    "range",  # a value outside its allowed interval, or a name that is not a valid key chunk
    "weights",  # sample weights negative or not summing to 1
    "covariance",  # a covariance that is not symmetric positive semi-definite
)

#: names that become key-expression chunks (robot, map): no '/', '*', '$', '?', '#'
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
#: NAME_PATTERN in words, for the errors and docs that state it
NAME_RULE = "letters, digits, '_', '.' and '-', starting with a letter or digit, at most 64"

#: the largest array a message may carry, in elements (bounds memory on hostile input)
MAX_ARRAY_ELEMENTS = 1 << 26


class MessageError(FormatError):
    """A wire message failed validation.

    Attributes: ``message_type`` (the declared type, or "?" when unknown) and ``reason`` (one of
    :data:`REASONS`). ``str(error)`` is one sentence saying what was wrong.
    """

    def __init__(self, message_type: str, reason: str, detail: str):
        assert reason in REASONS, reason
        self.message_type = message_type
        self.reason = reason
        super().__init__(f"{message_type} message rejected ({reason}): {detail}")


# ------------------------------------------------------------------------------------------ field specs


@dataclass(frozen=True)
class Spec(abc.ABC):
    """How one field is typed, validated and documented. Subclasses implement the three parts."""

    doc: str

    def to_wire(self, value: Any) -> Any:
        """The msgpack-ready form of a Python value."""
        return value

    @abc.abstractmethod
    def from_wire(self, name: str, value: Any, ctx: _DecodeContext) -> Any:
        """The validated Python value of a wire value; raises :class:`MessageError`."""

    @abc.abstractmethod
    def json_schema(self) -> dict:
        """This field's JSON Schema (draft 2020-12), msgpack values read as their JSON equivalents."""


@dataclass(frozen=True)
class Int(Spec):
    """An integer in [minimum, maximum] (either bound optional)."""

    minimum: int | None = None
    maximum: int | None = None

    def from_wire(self, name, value, ctx):
        if isinstance(value, bool) or not isinstance(value, int):
            ctx.fail("field_type", f"'{name}' must be an integer, got {type(value).__name__}")
        if (self.minimum is not None and value < self.minimum) or (self.maximum is not None and value > self.maximum):
            ctx.fail("range", f"'{name}' = {value} is outside [{self.minimum}, {self.maximum}]")
        return value

    def json_schema(self):
        return _bounded({"type": "integer", "description": self.doc}, minimum=self.minimum, maximum=self.maximum)


@dataclass(frozen=True)
class Float(Spec):
    """A finite float, optionally bounded below (``minimum``, or ``exclusive_minimum`` for > bound) and above
    (``maximum``)."""

    minimum: float | None = None
    exclusive_minimum: float | None = None
    maximum: float | None = None

    def to_wire(self, value):
        return float(value)

    def from_wire(self, name, value, ctx):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            ctx.fail("field_type", f"'{name}' must be a number, got {type(value).__name__}")
        value = float(value)
        if not math.isfinite(value):
            ctx.fail("nonfinite", f"'{name}' must be finite, got {value}")
        if self.minimum is not None and value < self.minimum:
            ctx.fail("range", f"'{name}' = {value} is below its minimum {self.minimum}")
        if self.exclusive_minimum is not None and value <= self.exclusive_minimum:
            ctx.fail("range", f"'{name}' = {value} must be greater than {self.exclusive_minimum}")
        if self.maximum is not None and value > self.maximum:
            ctx.fail("range", f"'{name}' = {value} is above its maximum {self.maximum}")
        return value

    def json_schema(self):
        return _bounded(
            {"type": "number", "description": self.doc + " (finite)"},
            minimum=self.minimum,
            exclusiveMinimum=self.exclusive_minimum,
            maximum=self.maximum,
        )


def _bounded(schema: dict[str, Any], **bounds: float | None) -> dict[str, Any]:
    """``schema`` with each of ``bounds`` that is set (JSON Schema keyword: value), in the order given."""
    return {**schema, **{keyword: value for keyword, value in bounds.items() if value is not None}}


@dataclass(frozen=True)
class Name(Spec):
    """A name that becomes one key-expression chunk (robot or map name); ``forbidden`` lists reserved names."""

    forbidden: tuple[str, ...] = ()

    def from_wire(self, name, value, ctx):
        if not isinstance(value, str):
            ctx.fail("field_type", f"'{name}' must be text, got {type(value).__name__}")
        if not is_valid_name(value) or value in self.forbidden:
            ctx.fail(
                "range",
                f"'{name}' = {value!r} is not a valid name ({NAME_RULE}; not {', '.join(self.forbidden) or 'empty'})",
            )
        return value

    def json_schema(self):
        out: dict[str, Any] = {"type": "string", "pattern": NAME_PATTERN, "description": self.doc}
        if self.forbidden:
            out["not"] = {"enum": list(self.forbidden)}
        return out


@dataclass(frozen=True)
class Counts(Spec):
    """A map from text labels to non-negative integer counts."""

    def to_wire(self, value):
        return {str(k): int(v) for k, v in value.items()}

    def from_wire(self, name, value, ctx):
        if not isinstance(value, dict):
            ctx.fail("field_type", f"'{name}' must be a map of counts, got {type(value).__name__}")
        for key, count in value.items():
            if not isinstance(key, str) or isinstance(count, bool) or not isinstance(count, int):
                ctx.fail("field_type", f"'{name}' must map text to integers, got {key!r}: {count!r}")
            if count < 0:
                ctx.fail("range", f"'{name}[{key}]' = {count} is negative")
        return dict(value)

    def json_schema(self):
        return {
            "type": "object",
            "description": self.doc,
            "additionalProperties": {"type": "integer", "minimum": 0},
        }


@dataclass(frozen=True)
class Figures(Spec):
    """A map from text labels to finite numbers."""

    def to_wire(self, value):
        return {str(k): float(v) for k, v in value.items()}

    def from_wire(self, name, value, ctx):
        if not isinstance(value, dict):
            ctx.fail("field_type", f"'{name}' must be a map of numbers, got {type(value).__name__}")
        for key, number in value.items():
            if not isinstance(key, str) or isinstance(number, bool) or not isinstance(number, (int, float)):
                ctx.fail("field_type", f"'{name}' must map text to numbers, got {key!r}: {number!r}")
            if not math.isfinite(number):
                ctx.fail("range", f"'{name}[{key}]' = {number} is not finite")
        return {key: float(number) for key, number in value.items()}

    def json_schema(self):
        return {"type": "object", "description": self.doc, "additionalProperties": {"type": "number"}}


@dataclass(frozen=True)
class Array(Spec):
    """A NumPy array of a fixed dtype and shape pattern.

    ``shape`` holds an int for a fixed length or a letter for a length that must agree across the
    message's fields (e.g. ``("M", 3)`` for samples and ``("M",)`` for their weights). ``values`` is
    "finite" (every value finite), "ranges" (finite values >= 0, NaN or +inf meaning no return, -inf a reading
    too close to measure) or "bits" (bytes of packed bits, any value). ``minimum`` bounds the
    finite values from below, ``magnitude`` their absolute values.
    """

    dtype: str = "<f8"
    shape: tuple[int | str, ...] = ()
    values: str = "finite"
    minimum: float | None = None
    magnitude: float | None = None

    def to_wire(self, value):
        array = np.ascontiguousarray(value, dtype=np.dtype(self.dtype))
        return {"dtype": self.dtype, "shape": list(array.shape), "data": array.tobytes()}

    def from_wire(self, name, value, ctx):
        if not isinstance(value, dict) or set(value) != {"dtype", "shape", "data"}:
            ctx.fail("field_type", f"'{name}' must be an array map with keys dtype, shape, data")
        dtype, shape, data = value["dtype"], value["shape"], value["data"]
        if dtype != self.dtype:
            ctx.fail("dtype", f"'{name}' must have dtype {self.dtype}, got {dtype!r}")
        if not isinstance(shape, list) or not all(
            isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape
        ):
            ctx.fail("shape", f"'{name}' shape must be a list of non-negative integers, got {shape!r}")
        if len(shape) != len(self.shape):
            ctx.fail("shape", f"'{name}' must have {len(self.shape)} dimensions {self.shape}, got {shape}")
        for want, got in zip(self.shape, shape):
            if isinstance(want, int) and got != want:
                ctx.fail("shape", f"'{name}' must have shape {self.shape}, got {shape}")
            if isinstance(want, str):
                ctx.bind_dim(want, got, name)
        if not isinstance(data, bytes):
            ctx.fail("field_type", f"'{name}' data must be binary, got {type(data).__name__}")
        count = math.prod(shape)
        if count > MAX_ARRAY_ELEMENTS:
            ctx.fail("size", f"'{name}' has {count} elements, more than the limit {MAX_ARRAY_ELEMENTS}")
        itemsize = np.dtype(self.dtype).itemsize
        if len(data) != count * itemsize:
            ctx.fail(
                "size", f"'{name}' data has {len(data)} bytes, shape {shape} of {self.dtype} needs {count * itemsize}"
            )
        array = np.frombuffer(data, np.dtype(self.dtype)).reshape(shape).copy()
        self._check_values(name, array, ctx)
        return array

    def _check_values(self, name: str, array: np.ndarray, ctx: _DecodeContext) -> None:
        if self.values == "bits":
            return
        finite = np.isfinite(array)
        if self.values == "finite" and not finite.all():
            ctx.fail("nonfinite", f"'{name}' has NaN or infinity at index {_first(~finite)}")
        if self.minimum is not None:
            below = finite & (array < self.minimum)
            if below.any():
                ctx.fail("range", f"'{name}' has {array[below][0]} at index {_first(below)}, below {self.minimum}")
        if self.magnitude is not None:
            beyond = finite & (np.abs(array) > self.magnitude)
            if beyond.any():
                ctx.fail(
                    "range",
                    f"'{name}' has {array[beyond][0]:.6g} at index {_first(beyond)}, beyond +-{self.magnitude:g}",
                )

    def json_schema(self):
        dims = [
            {"const": d} if isinstance(d, int) else {"type": "integer", "minimum": 0, "description": f"length {d}"}
            for d in self.shape
        ]
        values = {
            "finite": "every value finite",
            "ranges": "finite values >= 0, NaN or +inf for no return, -inf for too close to measure (REP 117)",
            "bits": "8 packed bits per byte, the least significant first",
        }[self.values]
        if self.minimum is not None:
            values += f", finite values >= {self.minimum}"
        if self.magnitude is not None:
            values += f", absolute values <= {self.magnitude:g}"
        return {
            "type": "object",
            "description": f"{self.doc}. NumPy array, dtype {self.dtype}, shape {list(self.shape)}; {values}",
            "required": ["dtype", "shape", "data"],
            "additionalProperties": False,
            "properties": {
                "dtype": {"const": self.dtype},
                "shape": {"type": "array", "prefixItems": dims, "items": False, "minItems": len(dims)},
                "data": {
                    "description": "msgpack bin: the raw little-endian C-order bytes, "
                    f"{np.dtype(self.dtype).itemsize} per element",
                    "contentMediaType": "application/octet-stream",
                },
            },
        }


def _first(mask: np.ndarray) -> tuple[int, ...] | int:
    index = tuple(int(i) for i in np.argwhere(mask)[0])
    return index[0] if len(index) == 1 else index


def is_valid_name(value: object) -> bool:
    """Whether ``value`` may be a robot or map name (one key-expression chunk, see :data:`NAME_PATTERN`)."""
    return isinstance(value, str) and re.fullmatch(NAME_PATTERN, value) is not None


def spec(field_spec: Spec, default: Any = dataclasses.MISSING, default_factory: Any = dataclasses.MISSING) -> Any:
    """A dataclass field carrying ``field_spec``; use as ``robot: str = spec(Name("robot name"))``. ``default`` (or
    ``default_factory``): what a constructor call that leaves the field out gets, for a field added to a message in a
    later version (code that builds the older form keeps working); the wire form always carries every field."""
    return dataclasses.field(default=default, default_factory=default_factory, metadata={"spec": field_spec})


# --------------------------------------------------------------------------------------------- messages


@dataclass(frozen=True)
class Rule:
    """A check across fields: ``check(values, fail)`` calls ``fail(reason, detail)`` when violated."""

    reason: str
    text: str  # what the rule requires, for the JSON Schema description
    check: Callable[[dict[str, Any], Callable[[str, str], None]], None]


class Message:
    """Base of every wire message. Subclasses are frozen dataclasses with spec'd fields and set
    ``TYPE`` (the wire name), ``VERSION`` and optionally ``RULES`` (cross-field checks)."""

    TYPE: ClassVar[str]
    VERSION: ClassVar[int]
    RULES: ClassVar[tuple[Rule, ...]] = ()
    # set by @dataclass on every subclass; declared here so that type checkers see Message as a dataclass
    __dataclass_fields__: ClassVar[dict[str, dataclasses.Field[Any]]]

    @classmethod
    def specs(cls) -> dict[str, Spec]:
        """The field specs in declaration order."""
        return {f.name: f.metadata["spec"] for f in dataclasses.fields(cls)}

    def encode(self) -> bytes:
        """The msgpack bytes of this message. Validates first: what encodes, decodes."""
        wire = self._wire()
        _validate(type(self), wire)
        return msgpack.packb(wire, use_bin_type=True)

    def digest(self) -> bytes:
        """16 bytes that stand for the message's type and fields (BLAKE2b of its wire form): messages with equal
        fields have equal digests, in any process, and different ones differ but by chance (2**-128)."""
        return hashlib.blake2b(msgpack.packb(self._wire(), use_bin_type=True), digest_size=16).digest()

    def _wire(self) -> dict[str, Any]:
        wire = {"type": self.TYPE, "v": self.VERSION}
        for name, field_spec in self.specs().items():
            wire[name] = field_spec.to_wire(getattr(self, name))
        return wire


class _DecodeContext:
    """State while decoding one message: its type name and the bound symbolic array lengths."""

    def __init__(self, message_type: str):
        self.message_type = message_type
        self.dims: dict[str, tuple[int, str]] = {}

    def fail(self, reason: str, detail: str):
        raise MessageError(self.message_type, reason, detail)

    def bind_dim(self, symbol: str, length: int, field_name: str) -> None:
        if symbol in self.dims and self.dims[symbol][0] != length:
            other_length, other_field = self.dims[symbol]
            self.fail("shape", f"'{field_name}' has length {symbol} = {length} but '{other_field}' has {other_length}")
        self.dims.setdefault(symbol, (length, field_name))


def _validate(cls: type[Message], wire: dict) -> dict[str, Any]:
    """Validate the field map of a ``cls`` message and return its Python field values."""
    ctx = _DecodeContext(cls.TYPE)
    specs = cls.specs()
    if wire.get("v") != cls.VERSION:
        ctx.fail("version", f"version {wire.get('v')!r} is not supported (this build reads version {cls.VERSION})")
    missing = [name for name in specs if name not in wire]
    if missing:
        ctx.fail("missing_field", f"missing field(s) {', '.join(missing)}")
    extra = sorted(str(k) for k in wire if k not in specs and k not in ("type", "v"))
    if extra:
        ctx.fail("unknown_field", f"unknown field(s) {', '.join(extra)}")
    values = {name: field_spec.from_wire(name, wire[name], ctx) for name, field_spec in specs.items()}
    for rule in cls.RULES:
        rule.check(values, ctx.fail)
    return values


def decode(payload: bytes, registry: dict[str, type[Message]], expected: tuple[type[Message], ...] = ()) -> Message:
    """Decode and validate one message of any type in ``registry``.

    ``expected``, when given, lists the types allowed (e.g. on one key); any other type is rejected
    with reason "type". Raises :class:`MessageError`; never returns a partly valid message.
    """
    try:
        wire = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as exc:  # noqa: BLE001 - msgpack raises several unrelated types for corrupt input
        detail = f"{type(exc).__name__}{': ' + str(exc) if str(exc) else ''}"
        raise MessageError("?", "malformed", f"not a msgpack document ({detail})") from None
    if not isinstance(wire, dict):
        raise MessageError("?", "malformed", f"expected a msgpack map, got {type(wire).__name__}")
    name, version = wire.get("type"), wire.get("v")
    if not isinstance(name, str) or isinstance(version, bool) or not isinstance(version, int):
        raise MessageError("?", "malformed", "the header needs 'type' (text) and 'v' (integer)")
    cls = registry.get(name)
    if cls is None:
        raise MessageError(name, "type", f"unknown message type {name!r}")
    if expected and cls not in expected:
        raise MessageError(name, "type", f"expected {' or '.join(t.TYPE for t in expected)}, got {name}")
    return cls(**_validate(cls, wire))
