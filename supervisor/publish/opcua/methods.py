"""The methods of a channel object, their arguments, and how a call becomes a command.

asyncua finds a method by its NodeId alone and checks neither the object it is called on
nor its arguments, so each call is checked here: the object (the method's own, else
Bad_MethodInvalid: ``not_on``), the number of arguments (Bad_ArgumentsMissing /
Bad_TooManyArguments) and each one's type (Bad_InvalidArgument, with Bad_TypeMismatch for
that argument). A call that passes becomes a ``Request`` for the command path, which checks
everything else (state, interlocks, role, values) and records it with its actor. Every
method answers one output argument, ``Result``: the command path's reason, accepted or not
— the only place an OPC UA client can read why a call was refused (a status code carries no
text). Part 9's Acknowledge, Confirm and ConditionRefresh(2) are declared here too, for the
same check.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

from asyncua import ua

from supervisor.publish.opcua.ports import Request
from supervisor.tags.spec import shown

VT = ua.VariantType
S = ua.StatusCodes


@dataclass(frozen=True, slots=True)
class Arg:
    name: str
    description: str
    types: tuple[ua.VariantType, ...]
    array_ok: bool = False  # a String array is also taken (ValueRank ScalarOrOneDimension)


@dataclass(frozen=True, slots=True)
class Method:
    name: str
    verb: str  # the command path's verb
    description: str
    args: tuple[Arg, ...] = ()
    optional: int = 0
    """The last ``optional`` arguments may be left out (added later: older callers work)."""


RECIPE = Arg(
    "Recipe",
    "A recipe file (recipes/x.yaml) or its name in the recipes folder; empty: the loaded one",
    (VT.String,),
)
PARAMETERS = Arg(
    "Parameters",
    'Overrides of recipe parameters: "v_max=1.8 V;q_max=1300 mAh", or one "k=v" per element',
    (VT.String,),
    array_ok=True,
)

# The test's metadata (issue 26): optional, empty is not given; checked by the command path.
METADATA_ARGS: Final = (
    (
        "CellId",
        "cell_id",
        "The cell or sample tested (at most 64 of A-Z a-z 0-9 space . _ : / + -)",
    ),
    ("Chemistry", "chemistry", "The cell's chemistry (e.g. nimh, liion)"),
    ("NominalCapacity", "nominal_capacity", "The cell's nominal capacity, e.g. 2.5 Ah or 1300 mAh"),
    ("Comment", "comment", "A free comment (at most 500 characters; newlines allowed)"),
)

METHODS: Final[tuple[Method, ...]] = (
    Method(
        "Start",
        "start",
        "Load a recipe (if given) and start its test",
        (RECIPE, PARAMETERS, *(Arg(n, d, (VT.String,)) for n, _, d in METADATA_ARGS)),
        optional=len(METADATA_ARGS),
    ),
    Method("Hold", "hold", "Hold the running test (ISA-88 Hold): current to 0 A"),
    Method("Resume", "resume", "Resume a held test where it was"),
    Method("Advance", "advance", "Leave the current step now (Chadèche CTRL-Z)"),
    Method("Stop", "stop", "Stop the test (ISA-88 Stop)"),
    Method("Abort", "abort", "Abort the test (ISA-88 Abort)"),
    Method("Reset", "reset", "Back to Idle after the end of a test; the channel in Manual"),
    Method(
        "SetMode",
        "mode",
        "Auto (the step chain drives the channel) or Manual (operator setpoints)",
        (Arg("Mode", "Auto or Manual", (VT.String,)),),
    ),
    Method(
        "SetManualCurrent",
        "manual_current",
        "The Manual setpoint in A (+ charges): Bad_OutOfRange beyond the channel's hard limits"
        " (its EURange), clamped within them to what the safety phase allows",
        (Arg("Current", "Current in A (+ charges)", (VT.Double, VT.Float)),),
    ),
    Method(
        "AcknowledgeAlarms",
        "acknowledge",
        "Acknowledge what holds the channel (its chain alarm and trips) and reset the trips"
        " whose cause is gone",
    ),
)
RESULT = Arg("Result", "What the bench did, or why it refused", (VT.String,))

TAG = Arg("Tag", "The tag's name (its NodeId's string, e.g. room.temp)", (VT.String,))
BENCH_METHODS: Final[tuple[Method, ...]] = (
    Method(
        "ForceTag",
        "force",
        "Engineers: force a tag to a value until UnforceTag (commissioning); never a tag the"
        " e-stop, an interlock or a channel's guard reads or drives",
        (
            TAG,
            Arg("Value", "The value as text, read as the tag's type (1.5, true, …)", (VT.String,)),
        ),
    ),
    Method("UnforceTag", "unforce", "Engineers: hand a forced tag back to the process", (TAG,)),
    # The bench-wide software e-stop (seed 002 §1.5), with the session's user as its actor.
    Method(
        "EmergencyStop",
        "estop",
        "Operators: press the software e-stop: every channel tripped as by the e-stop button"
        " (the estop alarm), recipes aborted, outputs safe; a second press names the first",
    ),
    Method(
        "ResetEmergencyStop",
        "estop_reset",
        "Operators: release the software e-stop and reset the estop trip, once acknowledged"
        " (Bad_InvalidState with the reason before, or while the e-stop button is pressed)",
    ),
)
"""The methods of the Bench object (ADR 0015)."""

EVENT_ID = Arg("EventId", "The EventId of the condition's event being answered", (VT.ByteString,))
COMMENT = Arg("Comment", "A comment (may be null)", (VT.LocalizedText, VT.Null))
ACKNOWLEDGE: Final = Method(
    "Acknowledge", "acknowledge", "Part 9 AcknowledgeableConditionType", (EVENT_ID, COMMENT)
)
CONFIRM: Final = Method(
    "Confirm", "reset", "Part 9 AcknowledgeableConditionType", (EVENT_ID, COMMENT)
)
"""Part 9's methods of a condition, declared so that ``check`` checks their arguments."""
_IDS = (VT.UInt32, VT.Int32, VT.UInt16, VT.Int16, VT.UInt64, VT.Int64, VT.Byte, VT.SByte)
SUBSCRIPTION = Arg("SubscriptionId", "The subscription to replay the conditions to", _IDS)
ITEM = Arg("MonitoredItemId", "The monitored item to replay them to", _IDS)
REFRESH: Final = Method("ConditionRefresh", "refresh", "Part 9 ConditionType", (SUBSCRIPTION,))
REFRESH2: Final = Method(
    "ConditionRefresh2", "refresh", "Part 9 ConditionType", (SUBSCRIPTION, ITEM)
)
"""ConditionType's refresh methods (an IntegerId is a UInt32; any integer is taken)."""

_TRUE: Final = ("true", "on", "yes", "1")
_FALSE: Final = ("false", "off", "no", "0")


KIND_WORDS: Final = {
    "analog": "a number",
    "int": "an integer",
    "state": "an integer",
    "bool": "true or false",
    "str": "a text",
}


def parse_value(text: str, kind: str) -> object:
    """A forced value written as text, in the type of a variable of ``kind`` (layout.py);
    ``ValueError`` when it is not one (the command path checks range and choices)."""
    t = text.strip()
    if kind == "analog":
        return float(t)
    if kind in ("int", "state"):
        return int(t)
    if kind == "bool":
        low = t.lower()
        if low not in (*_TRUE, *_FALSE):
            raise ValueError(text)
        return low in _TRUE
    return text


@dataclass(frozen=True, slots=True)
class Invalid:
    """A call refused before it is a command."""

    status: int
    reason: str
    arg_results: tuple[int, ...] = ()


def _type_name(v: ua.Variant) -> str:
    t = v.VariantType.name if v.VariantType is not None else "Null"
    return f"{t} array" if v.is_array or isinstance(v.Value, list) else t


def not_on(method: Method, called_on: ua.NodeId, owner: ua.NodeId) -> Invalid | None:
    """Part 4 §5.11.2 (Call): a method is called on an object it is a component of (or of
    whose type it is). A channel's method node is its own channel's: ch1's SetManualCurrent
    called on ch2's object would command ch1 while naming ch2 (issue 31, finding 5), so it
    is Bad_MethodInvalid and nothing is done."""
    if called_on == owner:
        return None
    return Invalid(
        S.BadMethodInvalid,
        f"{method.name} is a method of {owner.to_string()}, not of {called_on.to_string()}",
    )


def check(method: Method, args: Sequence[ua.Variant]) -> Invalid | None:
    """Why these arguments are not what ``method`` declares (None when they are)."""
    want, got = len(method.args), len(args)
    if got < want - method.optional:
        names = ", ".join(a.name for a in method.args[got : want - method.optional])
        return Invalid(S.BadArgumentsMissing, f"{method.name}: missing argument {names}")
    if got > want:
        return Invalid(
            S.BadTooManyArguments,
            f"{method.name}: takes {want} argument{'s' if want != 1 else ''}, got {got}",
        )
    results: list[int] = []
    wrong: list[str] = []
    for a, v in zip(method.args, args, strict=False):
        is_list = v.is_array or isinstance(v.Value, list)
        ok = v.VariantType in a.types and (not is_list or a.array_ok)
        if ok and is_list:
            ok = all(isinstance(x, str) for x in v.Value)
        results.append(S.Good if ok else S.BadTypeMismatch)
        if not ok:
            expected = " or ".join(t.name for t in a.types) + (
                " (or a String array)" if a.array_ok else ""
            )
            wrong.append(f"{a.name} must be a {expected}, got {_type_name(v)} {shown(v.Value)}")
    if wrong:
        return Invalid(S.BadInvalidArgument, f"{method.name}: " + "; ".join(wrong), tuple(results))
    return None


def parse_parameters(value: object) -> dict[str, str]:
    """``"k=v;k=v"`` or ``["k=v", ...]`` → {k: v}; ValueError naming the bad item."""
    items = value if isinstance(value, list) else str(value).split(";")
    out: dict[str, str] = {}
    for raw in items:
        item = str(raw).strip()
        if not item:
            continue
        key, eq, val = item.partition("=")
        if not eq or not key.strip():
            raise ValueError(f"parameter {shown(item)} is not name=value (e.g. v_max=1.8 V)")
        out[key.strip()] = val.strip()
    return out


def request(
    method: Method, channel: str, args: Sequence[ua.Variant], actor: str
) -> Request | Invalid:
    """The command of a call whose argument types ``check`` accepted. A recipe is passed
    as the client named it: the command path finds a name in the recipe folders and
    refuses a path outside them (its path policy, ADR 0026)."""
    values = [v.Value for v in args]
    if method.verb == "start":
        recipe, params = str(values[0] or ""), values[1]
        try:
            parameters = parse_parameters(params if params is not None else "")
        except ValueError as exc:
            return Invalid(S.BadInvalidArgument, f"Start: {exc}", (S.Good, S.BadInvalidArgument))
        metadata: dict[str, object] = {
            key: values[i]
            for i, (_, key, _) in enumerate(METADATA_ARGS, start=2)
            if i < len(values) and values[i] not in (None, "")
        }
        if not recipe:
            if parameters:
                return Invalid(
                    S.BadInvalidArgument,
                    "Start: parameters are given with a recipe (the loaded one has its own)",
                    (S.Good, S.BadInvalidArgument),
                )
            return Request("channel", channel, "start", metadata, actor)
        return Request(
            "channel",
            channel,
            "start",
            {"recipe": recipe, "parameters": parameters, **metadata},
            actor,
        )
    if method.verb == "mode":
        mode = str(values[0])
        # "Auto"/"Manual" as SCADA screens write them; the command path checks the value.
        return Request("channel", channel, "mode", {"value": mode.strip().lower()}, actor)
    if method.verb in ("force", "unforce"):
        tag = str(values[0])
        fargs: dict[str, object] = {"tag": tag}
        if method.verb == "force":
            fargs["value"] = values[1]  # parsed by the server, which knows the tag's type
        return Request("bench", "", method.verb, fargs, actor)
    if method.verb in ("estop", "estop_reset"):
        return Request("bench", "", method.verb, {}, actor)
    if method.verb == "manual_current":
        return Request("channel", channel, "manual_current", {"value": float(values[0])}, actor)
    return Request("channel", channel, method.verb, {}, actor)


def argument(a: Arg) -> ua.Argument:
    """The ``InputArguments``/``OutputArguments`` entry of ``a``."""
    arg = ua.Argument()
    arg.Name = a.name
    arg.DataType = ua.NodeId(a.types[0].value)
    arg.ValueRank = ua.ValueRank.ScalarOrOneDimension if a.array_ok else ua.ValueRank.Scalar
    arg.ArrayDimensions = []
    arg.Description = ua.LocalizedText(a.description)
    return arg
