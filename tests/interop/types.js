// Object types, naming, identification and the Server object as node-opcua-client (not
// asyncua) sees them, for tests/interop/test_opcua_types_interop.py: it browses the Bench,
// a channel and its type, the devices and their types, the diagnostics, reads the bench's
// Identification, the Server object (BuildInfo, ServerCapabilities, diagnostics, Auditing,
// HistoryServerCapabilities) and the EURange of analog tags, then prints one JSON line of
// what it saw and exits. The test decides what is right; this script only looks.
//
// node types.js '{"endpoint": ..., "namespace": ..., "user": ..., "password": ...,
//                 "applicationUri": ..., "cert": ..., "key": ..., "pki": ...}'
"use strict";
const { open } = require("./client.js");
const {
  AttributeIds,
  BrowseDirection,
  NodeClass,
} = require("node-opcua-client");

const cfg = JSON.parse(process.argv[2]);
const out = { steps: [] };
const say = (step) => out.steps.push(step);

// A value as JSON: numbers, texts and arrays as they are; a LocalizedText as its text, a
// NodeId as its string, a Date in ms, a structure as its own fields.
function plain(v) {
  if (v === null || v === undefined) return null;
  if (Array.isArray(v) || ArrayBuffer.isView(v)) return Array.from(v, plain);
  if (v instanceof Date) return v.getTime();
  if (typeof v === "bigint") return Number(v);
  if (typeof v !== "object") return v;
  if (v.constructor && v.constructor.name === "LocalizedText") return v.text;
  if (v.constructor && v.constructor.name === "NodeId") return v.toString();
  if (v.constructor && v.constructor.name === "QualifiedName") return v.name;
  if (Array.isArray(v) && v.length === 2 && typeof v[0] === "number") return v[0] * 4294967296 + v[1];
  const o = {};
  for (const k of Object.keys(v)) {
    if (k.startsWith("_") || k === "schema") continue;
    o[k] = plain(v[k]);
  }
  return o;
}

async function main() {
  const { client, session } = await open(cfg, "types", say);
  const namespaces = await session.readNamespaceArray();
  out.namespaces = namespaces;
  const ns = namespaces.indexOf(cfg.namespace);
  const id = (s) => `ns=${ns};s=${s}`;
  const uriOf = (q) => namespaces[q.namespaceIndex];

  // The forward hierarchical children of a node: browse name (and its namespace's URI),
  // NodeId, node class, type definition.
  async function children(nodeId) {
    const found = [];
    let r = await session.browse({
      nodeId,
      browseDirection: BrowseDirection.Forward,
      referenceTypeId: "HierarchicalReferences",
      includeSubtypes: true,
      resultMask: 0x3f,
    });
    for (;;) {
      for (const ref of r.references || []) {
        found.push({
          name: ref.browseName.name,
          uri: uriOf(ref.browseName),
          nodeId: ref.nodeId.toString(),
          nodeClass: NodeClass[ref.nodeClass],
          type: ref.typeDefinition ? ref.typeDefinition.toString() : null,
        });
      }
      if (!r.continuationPoint || r.continuationPoint.length === 0) break;
      r = await session.browseNext(r.continuationPoint, false);
    }
    return found;
  }
  async function browseName(nodeId) {
    const dv = await session.read({ nodeId, attributeId: AttributeIds.BrowseName });
    return { name: dv.value.value.name, uri: namespaces[dv.value.value.namespaceIndex] };
  }
  async function typeDefinition(nodeId) {
    const r = await session.browse({
      nodeId,
      browseDirection: BrowseDirection.Forward,
      referenceTypeId: "HasTypeDefinition",
      resultMask: 0x3f,
    });
    if (!r.references || r.references.length === 0) return null;
    const t = r.references[0].nodeId;
    return { nodeId: t.toString(), ...(await browseName(t)) };
  }
  async function supertype(nodeId) {
    const r = await session.browse({
      nodeId,
      browseDirection: BrowseDirection.Inverse,
      referenceTypeId: "HasSubtype",
      resultMask: 0x3f,
    });
    if (!r.references || r.references.length === 0) return null;
    const t = r.references[0].nodeId;
    return { nodeId: t.toString(), ...(await browseName(t)) };
  }
  async function modellingRule(nodeId) {
    const r = await session.browse({
      nodeId,
      browseDirection: BrowseDirection.Forward,
      referenceTypeId: "HasModellingRule",
      resultMask: 0x3f,
    });
    return r.references.length ? r.references[0].browseName.name : null;
  }
  async function value(nodeId) {
    const dv = await session.read({ nodeId, attributeId: AttributeIds.Value });
    return { status: dv.statusCode.name, value: plain(dv.value ? dv.value.value : null) };
  }
  // Each variable child's value, by browse name.
  async function values(nodeId) {
    const o = {};
    for (const c of await children(nodeId)) {
      if (c.nodeClass === "Variable") o[c.name] = await value(c.nodeId);
    }
    return o;
  }
  async function described(nodeId) {
    const kids = await children(nodeId);
    const type = await typeDefinition(nodeId);
    return { type, children: kids };
  }

  // The bench, a channel, their types.
  out.bench = await described(id("/Bench"));
  const channels = await children(id("/Bench/Channels"));
  out.channels = channels.map((c) => c.name);
  out.ch0 = await described(channels[0].nodeId);
  out.ch1Type = (await typeDefinition(channels[1].nodeId)).nodeId;
  const channelType = out.ch0.type.nodeId;
  out.channelType = {
    supertype: await supertype(channelType),
    children: await children(channelType),
    rules: {},
  };
  for (const c of out.channelType.children) out.channelType.rules[c.name] = await modellingRule(c.nodeId);
  out.benchTypeSupertype = await supertype(out.bench.type.nodeId);
  say("channel");

  // The channel's state machine: its type, its current state and that state's Id and Number.
  const machine = out.ch0.children.find((c) => c.name === "StateMachine");
  if (machine) {
    out.stateMachine = await described(machine.nodeId);
    out.stateMachine.supertype = await supertype(out.stateMachine.type.nodeId);
    const current = out.stateMachine.children.find((c) => c.name === "CurrentState");
    if (current) {
      out.stateMachine.current = await value(current.nodeId);
      out.stateMachine.currentType = await typeDefinition(current.nodeId);
      out.stateMachine.currentProperties = await values(current.nodeId);
      const idValue = out.stateMachine.currentProperties.Id;
      if (idValue && idValue.value) out.stateMachine.currentStateName = await browseName(idValue.value);
    }
    const states = await children(out.stateMachine.type.nodeId);
    out.stateMachine.typeStates = states.filter((s) => s.nodeClass === "Object").map((s) => s.name);
  }
  say("state machine");

  // The devices and their types, the diagnostics, the alarms.
  out.devices = {};
  for (const d of await children(id("/Bench/Devices"))) {
    const t = await typeDefinition(d.nodeId);
    out.devices[d.name] = {
      type: t,
      supertype: t && (await supertype(t.nodeId)),
      children: (await children(d.nodeId)).map((c) => c.name),
    };
  }
  out.diagnostics = (await children(id("/Bench/Diagnostics"))).map((c) => ({ name: c.name, nodeId: c.nodeId }));
  out.alarms = {};
  out.conditions = {};
  for (const a of await children(id("/Bench/Alarms"))) {
    const t = await typeDefinition(a.nodeId);
    out.alarms[a.name] = t && t.nodeId;
    // The condition's variables as a client reads them on the object (Part 9), each
    // state's Id beside it.
    const v = await values(a.nodeId);
    for (const state of ["EnabledState", "ActiveState", "AckedState"]) {
      const node = (await children(a.nodeId)).find((c) => c.name === state);
      if (node) v[`${state}/Id`] = (await values(node.nodeId)).Id;
    }
    out.conditions[a.name] = v;
  }
  say("devices");

  // Identification (OPC 40001-1): the Bench's component, and the Machines folder.
  const ident = out.bench.children.find((c) => c.name === "Identification");
  if (ident) {
    out.identification = {
      uri: ident.uri,
      type: await typeDefinition(ident.nodeId),
      values: await values(ident.nodeId),
    };
  }
  const objects = await children("i=85");
  const machines = objects.find((c) => c.name === "Machines");
  if (machines) {
    out.machines = { uri: machines.uri, children: (await children(machines.nodeId)).map((c) => c.nodeId) };
  }
  out.benchNodeId = id("/Bench");
  say("identification");

  // The Server object.
  out.buildInfo = await values("i=2260");
  out.capabilities = await values("i=2268");
  out.operationLimits = await values("i=11704");
  out.historyCapabilities = await values("i=11192");
  out.diagnosticsEnabled = await value("i=2294");
  out.diagnosticsSummary = await value("i=2275");
  out.auditing = await value("i=2994");
  say("server");

  // EURange of analog tags, and what a tag without a known range is.
  out.analog = {};
  for (const tag of cfg.analog) {
    const kids = await children(id(tag));
    const range = kids.find((c) => c.name === "EURange");
    const t = await typeDefinition(id(tag));
    out.analog[tag] = {
      type: t && t.name,
      children: kids.map((c) => c.name),
      range: range ? (await value(range.nodeId)).value : null,
    };
  }
  say("analog");

  await session.close();
  await client.disconnect();
  say("closed");
}

main()
  .then(() => {
    console.log(JSON.stringify(out));
    process.exit(0);
  })
  .catch((err) => {
    out.error = String(err && err.stack ? err.stack : err);
    console.log(JSON.stringify(out));
    process.exit(1);
  });
