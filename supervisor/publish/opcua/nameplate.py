"""What the server says about itself and about the bench (issue 31, finding 7 and
"Identification"): the Server object filled with what is true, and the bench's
Identification as OPC 40001-1 (Machinery) asks it.

- **BuildInfo**: the product (``bench-supervisor``), its version from the package's metadata
  (also the build number), the date its distribution was installed (the build a bench
  runs), not asyncua's ``FreeOpcUa Python Server 1.0pre``.
- **ServerCapabilities**: the profile served, the locale, the shortest sampling interval
  (the feed's: the server never samples faster), query and history continuation points.
  The operation limits and MaxBrowseContinuationPoints are the service layer's (what it
  enforces); only one still null is written here (0: no limit declared).
- **ServerDiagnostics**: not collected (asyncua counts neither sessions nor rejected
  requests); ``EnabledFlag`` false, and the summary answers Bad_NotSupported rather than a
  Good null or made-up zeros. **Auditing**: false (no audit events are generated).
- **HistoryServerCapabilities**: what history.py serves: raw data and events read when the
  bench records its history, nothing inserted, replaced or deleted.
- **Identification** (``MachineIdentificationType``): the Bench object's ``Identification``
  add-in with Manufacturer, Model, SerialNumber, ProductInstanceUri, SoftwareRevision,
  Location … from the I/O map's ``identification:``; Objects/Machines organizes the Bench,
  Machinery's entry point. The two companion namespaces (DI, Machinery) are registered and
  the few types used are declared here under their standard NodeIds (DI's
  FunctionalGroupType i=1005, Machinery's MachineIdentificationType i=1012 and Machines
  i=1001): loading their nodesets would ship other organisations' files and cost start-up
  time for types the bench does not use.
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Final

from asyncua import Server, ua

from supervisor.publish.opcua.settings import Identification, OpcUaSettings

log = logging.getLogger(__name__)

O = ua.ObjectIds  # noqa: E741 - asyncua's own abbreviation
VT = ua.VariantType

PRODUCT: Final = "bench-supervisor"
PRODUCT_URI: Final = "urn:bench-supervisor"
MANUFACTURER: Final = "bench-supervisor project"
DI_URI: Final = "http://opcfoundation.org/UA/DI/"
MACHINERY_URI: Final = "http://opcfoundation.org/UA/Machinery/"
FUNCTIONAL_GROUP_TYPE: Final = 1005  # DI
MACHINE_IDENTIFICATION_TYPE: Final = 1012  # Machinery
MACHINES: Final = 1001  # Machinery's Objects/Machines folder

PROFILES: Final = ("http://opcfoundation.org/UA-Profile/Server/EmbeddedUA2017",)
"""The server profile whose facets the server offers (not a certification)."""
LOCALES: Final = ("en",)


def software_version() -> str:
    """The installed package's version (its metadata), "unknown" when run from a tree that
    was never installed."""
    try:
        return metadata.version(PRODUCT)
    except metadata.PackageNotFoundError:
        return "unknown"


def build_date() -> datetime:
    """When the installed distribution was built into this environment: its metadata
    file's time (the epoch when unknown)."""
    try:
        files = metadata.distribution(PRODUCT).files or []
        record = next((f for f in files if f.name == "METADATA"), None)
        when = Path(record.locate()).stat().st_mtime if record is not None else 0.0
    except (metadata.PackageNotFoundError, OSError):
        when = 0.0
    return datetime.fromtimestamp(when, UTC)


async def _write(server: Server, nid: ua.NodeId | int, variant: ua.Variant) -> None:
    node = nid if isinstance(nid, ua.NodeId) else ua.NodeId(nid)
    await server.iserver.aspace.write_attribute_value(
        node, ua.AttributeIds.Value, ua.DataValue(variant)
    )


async def fill_server_object(
    server: Server, settings: OpcUaSettings, *, history: bool, page: int
) -> None:
    """BuildInfo, ServerCapabilities, diagnostics, Auditing and HistoryServerCapabilities.
    ``history``: the bench records history (HistoryRead served); ``page``: the most values
    one HistoryRead answer holds."""
    version = software_version()
    await server.set_build_info(PRODUCT_URI, MANUFACTURER, PRODUCT, version, version, build_date())
    caps = {
        O.Server_ServerCapabilities_ServerProfileArray: ua.Variant(list(PROFILES), VT.String),
        O.Server_ServerCapabilities_LocaleIdArray: ua.Variant(list(LOCALES), VT.String),
        # The feed's interval: the server never samples the scan faster.
        O.Server_ServerCapabilities_MinSupportedSampleRate: ua.Variant(
            1000.0 * (settings.sampling_interval_s or settings.scan_period_s), VT.Double
        ),
    }
    for nid, variant in caps.items():
        await _write(server, nid, variant)
    for nid, value in (
        (O.Server_ServerCapabilities_MaxQueryContinuationPoints, 0),  # no Query service
        # HistoryRead's continuation points are stateless (history.py): no limit (0).
        (O.Server_ServerCapabilities_MaxHistoryContinuationPoints, 0),
    ):
        await _write(server, nid, ua.Variant(value, VT.UInt16))
    await _write(server, O.Server_ServerCapabilities_MaxArrayLength, ua.Variant(0, VT.UInt32))
    await _write(server, O.Server_ServerCapabilities_MaxStringLength, ua.Variant(0, VT.UInt32))
    await _write(server, O.Server_ServerCapabilities_MaxByteStringLength, ua.Variant(0, VT.UInt32))
    await _write(
        server,
        O.Server_ServerCapabilities_SoftwareCertificates,
        ua.Variant([], VT.ExtensionObject),
    )
    await _fill_null_limits(server)
    # Diagnostics are not collected: say so, rather than a Good null or counts of zero.
    await _write(server, O.Server_ServerDiagnostics_EnabledFlag, ua.Variant(False, VT.Boolean))
    await server.iserver.aspace.write_attribute_value(
        ua.NodeId(O.Server_ServerDiagnostics_ServerDiagnosticsSummary),
        ua.AttributeIds.Value,
        ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadNotSupported)),
    )
    await _write(server, O.Server_Auditing, ua.Variant(False, VT.Boolean))
    await _fill_history_capabilities(server, history, page)


async def _fill_null_limits(server: Server) -> None:
    """An operation limit or MaxBrowseContinuationPoints still null is 0 (Part 5: no limit
    declared) so that it reads Good: the ones the service layer enforces are written there
    (services.py), before this runs, and left alone."""
    limits = server.get_node(ua.NodeId(O.Server_ServerCapabilities_OperationLimits))
    nodes = [c.nodeid for c in await limits.get_children(refs=O.HasProperty)]
    points = ua.NodeId(O.Server_ServerCapabilities_MaxBrowseContinuationPoints)
    for nid in (*nodes, points):
        dv = await server.get_node(nid).read_data_value(raise_on_bad_status=False)
        if dv.Value is None or dv.Value.Value is None:
            vt = VT.UInt16 if nid == points else VT.UInt32
            await _write(server, nid, ua.Variant(0, vt))


HISTORY_FLAGS: Final = (
    "InsertDataCapability",
    "ReplaceDataCapability",
    "UpdateDataCapability",
    "DeleteRawCapability",
    "DeleteAtTimeCapability",
    "InsertEventCapability",
    "ReplaceEventCapability",
    "UpdateEventCapability",
    "DeleteEventCapability",
    "InsertAnnotationCapability",
    "ServerTimestampSupported",
)
"""What HistoryUpdate would offer (history.py serves no HistoryUpdate) and server
timestamps in history (the historian keeps source times only)."""


async def _fill_history_capabilities(server: Server, history: bool, page: int) -> None:
    node = server.get_node(ua.NodeId(O.HistoryServerCapabilities))
    wanted: dict[str, ua.Variant] = {
        "AccessHistoryDataCapability": ua.Variant(history, VT.Boolean),
        "AccessHistoryEventsCapability": ua.Variant(history, VT.Boolean),
        "MaxReturnDataValues": ua.Variant(page if history else 0, VT.UInt32),
        "MaxReturnEventValues": ua.Variant(page if history else 0, VT.UInt32),
        **{name: ua.Variant(False, VT.Boolean) for name in HISTORY_FLAGS},
    }
    for child in await node.get_children(refs=O.HasProperty):
        name = (await child.read_browse_name()).Name
        if name in wanted:
            await _write(server, child.nodeid, wanted[name])


def _property(
    nid: ua.NodeId, name: ua.QualifiedName, parent: ua.NodeId, variant: ua.Variant, dtype: int
) -> ua.AddNodesItem:
    it = ua.AddNodesItem()
    it.RequestedNewNodeId = nid
    it.BrowseName = name
    it.NodeClass = ua.NodeClass.Variable
    it.ParentNodeId = parent
    it.ReferenceTypeId = ua.NodeId(O.HasProperty)
    it.TypeDefinition = ua.NodeId(O.PropertyType)
    a = ua.VariableAttributes()
    a.DisplayName = ua.LocalizedText(name.Name)
    a.Description = ua.LocalizedText(name.Name)
    a.DataType = ua.NodeId(dtype)
    a.Value = variant
    a.ValueRank = ua.ValueRank.Scalar
    a.AccessLevel = ua.AccessLevel.CurrentRead.mask
    a.UserAccessLevel = ua.AccessLevel.CurrentRead.mask
    it.NodeAttributes = a
    return it


def _node(
    nid: ua.NodeId,
    name: ua.QualifiedName,
    parent: ua.NodeId,
    ref: int,
    node_class: ua.NodeClass,
    typedef: ua.NodeId | None = None,
    abstract: bool = False,
) -> ua.AddNodesItem:
    it = ua.AddNodesItem()
    it.RequestedNewNodeId = nid
    it.BrowseName = name
    it.NodeClass = node_class
    it.ParentNodeId = parent
    it.ReferenceTypeId = ua.NodeId(ref)
    if node_class is ua.NodeClass.ObjectType:
        a: ua.ObjectTypeAttributes | ua.ObjectAttributes = ua.ObjectTypeAttributes()
        a.IsAbstract = abstract
    else:
        a = ua.ObjectAttributes()
        it.TypeDefinition = typedef or ua.NodeId(O.BaseObjectType)
    a.DisplayName = ua.LocalizedText(name.Name)
    a.Description = ua.LocalizedText(name.Name)
    it.NodeAttributes = a
    return it


def identification_values(
    ident: Identification, bench: str, namespace: str
) -> list[tuple[str, str, ua.Variant, int]]:
    """(namespace: "di" or "machinery", browse name, value, DataType) of each property the
    bench's Identification has: the configured ones, the serial number (default: the
    bench's name), the product instance URI (default: the bench's namespace) and the
    software revision (the supervisor's version)."""
    LT, S = VT.LocalizedText, VT.String
    rows: list[tuple[str, str, ua.Variant, int]] = [
        (
            "di",
            "Manufacturer",
            ua.Variant(ua.LocalizedText(ident.manufacturer), LT),
            O.LocalizedText,
        ),
        ("di", "SerialNumber", ua.Variant(ident.serial_number or bench, S), O.String),
        (
            "di",
            "ProductInstanceUri",
            ua.Variant(ident.product_instance_uri or namespace, S),
            O.String,
        ),
        ("di", "SoftwareRevision", ua.Variant(software_version(), S), O.String),
    ]
    if ident.model:
        rows.append(("di", "Model", ua.Variant(ua.LocalizedText(ident.model), LT), O.LocalizedText))
    if ident.manufacturer_uri:
        rows.append(("di", "ManufacturerUri", ua.Variant(ident.manufacturer_uri, S), O.String))
    if ident.asset_id:
        rows.append(("di", "AssetId", ua.Variant(ident.asset_id, S), O.String))
    if ident.location:
        rows.append(("machinery", "Location", ua.Variant(ident.location, S), O.String))
    if ident.year_of_construction is not None:
        rows.append(
            (
                "machinery",
                "YearOfConstruction",
                ua.Variant(ident.year_of_construction, VT.UInt16),
                O.UInt16,
            )
        )
    return rows


async def add_identification(
    server: Server, settings: OpcUaSettings, bench: ua.NodeId, namespace: str
) -> ua.NodeId:
    """The DI and Machinery namespaces, MachineIdentificationType, the Bench's
    Identification add-in with its properties, and Objects/Machines organizing the Bench.
    Returns the Identification object's NodeId."""
    di = await server.register_namespace(DI_URI)
    machinery = await server.register_namespace(MACHINERY_URI)
    group_type = ua.NodeId(FUNCTIONAL_GROUP_TYPE, di)
    ident_type = ua.NodeId(MACHINE_IDENTIFICATION_TYPE, machinery)
    machines = ua.NodeId(MACHINES, machinery)
    ident = ua.NodeId(f"{bench.Identifier}/Identification", bench.NamespaceIndex)
    items = [
        _node(
            group_type,
            ua.QualifiedName("FunctionalGroupType", di),
            ua.NodeId(O.FolderType),
            O.HasSubtype,
            ua.NodeClass.ObjectType,
        ),
        _node(
            ident_type,
            ua.QualifiedName("MachineIdentificationType", machinery),
            group_type,
            O.HasSubtype,
            ua.NodeClass.ObjectType,
        ),
        _node(
            machines,
            ua.QualifiedName("Machines", machinery),
            ua.NodeId(O.ObjectsFolder),
            O.Organizes,
            ua.NodeClass.Object,
            ua.NodeId(O.FolderType),
        ),
        _node(
            ident,
            ua.QualifiedName("Identification", di),
            bench,
            O.HasAddIn,
            ua.NodeClass.Object,
            ident_type,
        ),
    ]
    items += _identification_properties(
        identification_values(settings.identification, settings.bench, namespace),
        ident,
        {"di": di, "machinery": machinery},
    )
    results = await server.iserver.isession.add_nodes(items)
    bad = [r.StatusCode for r in results if not r.StatusCode.is_good()]
    if bad:
        raise RuntimeError(f"OPC UA identification: {len(bad)} nodes refused, first {bad[0]}")
    await _organize(server, machines, bench)
    return ident


def _identification_properties(
    values: list[tuple[str, str, ua.Variant, int]], ident: ua.NodeId, where: dict[str, int]
) -> list[ua.AddNodesItem]:
    """The Identification object's properties (``identification_values``), each browse name
    in its companion namespace's index (``where``: "di", "machinery"), each NodeId under the
    Identification's in the bench's namespace."""
    return [
        _property(
            ua.NodeId(f"{ident.Identifier}/{name}", ident.NamespaceIndex),
            ua.QualifiedName(name, where[ns]),
            ident,
            variant,
            dtype,
        )
        for ns, name, variant, dtype in values
    ]


async def _organize(server: Server, folder: ua.NodeId, target: ua.NodeId) -> None:
    """``folder`` Organizes the object ``target`` (Objects/Machines the Bench)."""
    ref = ua.AddReferencesItem()
    ref.IsForward = True
    ref.ReferenceTypeId = ua.NodeId(O.Organizes)
    ref.SourceNodeId = folder
    ref.TargetNodeClass = ua.NodeClass.Object
    ref.TargetNodeId = target
    await server.iserver.isession.add_references([ref])
