// Alarms & Conditions, method ownership and history as an integrator's node-opcua client
// exercises them, for tests/interop/test_opcua_conditions_interop.py (issue 31, findings 3,
// 5, 7 and 8): it runs the actions it is given in one session, in order, and prints one
// JSON line with each action's outcome. The test drives the bench between two runs.
//
// node conditions.js '{"endpoint": ..., "namespace": ..., "user": ..., "password": ...,
//                      "applicationUri": ..., "cert": ..., "key": ..., "pki": ...,
//                      "actions": [{"do": "refresh"}, {"do": "call", ...}, ...]}'
//
// Actions (a node is "ns=0;i=…" or, with "s:" in front, a string id of the bench's
// namespace, e.g. "s:/Bench/Alarms/estop"):
//   {"do": "refresh"}: a subscription to the Server's events, ConditionRefresh, and the
//       conditions replayed between RefreshStartEvent and RefreshEndEvent;
//   {"do": "call", "object": node, "method": node, "args": [{"type": "ByteString",
//       "hex": …} | {"type": "String" | "LocalizedText" | "Double", "value": …}]};
//   {"do": "browse", "node": node}: the browse names of its forward hierarchical references;
//   {"do": "processed", "node": node, "aggregate": node, "start": ms, "end": ms,
//       "intervalMs": …}: HistoryRead ReadProcessedDetails;
//   {"do": "raw", "node": node, "start": ms, "end": ms}: HistoryRead ReadRawModifiedDetails.
"use strict";
const { open } = require("./client.js");
const {
  AttributeIds,
  BrowseDirection,
  DataType,
  HistoryReadRequest,
  LocalizedText,
  ReadProcessedDetails,
  TimestampsToReturn,
  constructEventFilter,
} = require("node-opcua-client");

const cfg = JSON.parse(process.argv[2]);
const out = { steps: [], results: [] };
const say = (step) => out.steps.push(step);
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
const REFRESH_START = "ns=0;i=2787";
const REFRESH_END = "ns=0;i=2788";

async function until(what, cond, ms) {
  const t0 = Date.now();
  while (!cond()) {
    if (Date.now() - t0 > ms) throw new Error(`gave up waiting for ${what}`);
    await sleep(50);
  }
}

function variant(a) {
  if (a.type === "ByteString") return { dataType: DataType.ByteString, value: Buffer.from(a.hex, "hex") };
  if (a.type === "LocalizedText") return { dataType: DataType.LocalizedText, value: new LocalizedText({ text: a.value }) };
  return { dataType: DataType[a.type], value: a.value };
}

const FIELDS = ["EventId", "EventType", "ConditionName", "ConditionId", "Retain", "ActiveState.Id", "AckedState.Id"];

function eventOf(values) {
  const e = {};
  FIELDS.forEach((f, k) => {
    const v = values[k].value;
    if (v === null || typeof v === "number" || typeof v === "boolean") e[f] = v;
    else if (Buffer.isBuffer(v)) e[f] = v.toString("hex");
    else e[f] = v.toString();
  });
  return e;
}

async function refresh(session) {
  const subscription = await session.createSubscription2({
    requestedPublishingInterval: 50,
    requestedMaxKeepAliveCount: 20,
    requestedLifetimeCount: 600,
    publishingEnabled: true,
  });
  const events = [];
  const item = await subscription.monitor(
    { nodeId: "ns=0;i=2253", attributeId: AttributeIds.EventNotifier },
    { queueSize: 1000, filter: constructEventFilter(FIELDS) },
    TimestampsToReturn.Both,
  );
  item.on("changed", (values) => events.push(eventOf(values)));
  const call = await session.call({
    objectId: "ns=0;i=2782", // ConditionType
    methodId: "ns=0;i=3875", // ConditionType.ConditionRefresh
    inputArguments: [{ dataType: DataType.UInt32, value: subscription.subscriptionId }],
  });
  await until("RefreshEndEvent", () => events.some((e) => e.EventType === REFRESH_END), 20000);
  const first = events.findIndex((e) => e.EventType === REFRESH_START);
  const last = events.findIndex((e) => e.EventType === REFRESH_END);
  await subscription.terminate();
  return { status: call.statusCode.name, conditions: events.slice(first + 1, last) };
}

async function history(session, nodeId, details) {
  const request = new HistoryReadRequest({
    nodesToRead: [{ nodeId }],
    historyReadDetails: details,
    timestampsToReturn: TimestampsToReturn.Source,
    releaseContinuationPoints: false,
  });
  const response = await new Promise((resolve, reject) =>
    session.historyRead(request, (err, res) => (err ? reject(err) : resolve(res))),
  );
  const r = response.results[0];
  const values = r.historyData && r.historyData.dataValues ? r.historyData.dataValues : [];
  return {
    status: r.statusCode.name,
    values: values.map((dv) => ({
      value: dv.value ? dv.value.value : null,
      type: dv.value ? DataType[dv.value.dataType] : null,
      status: dv.statusCode.name,
    })),
  };
}

async function run(session, action, id) {
  if (action.do === "refresh") return refresh(session);
  if (action.do === "call") {
    const res = await session.call({
      objectId: id(action.object),
      methodId: id(action.method),
      inputArguments: (action.args || []).map(variant),
    });
    return {
      status: res.statusCode.name,
      inputs: (res.inputArgumentResults || []).map((s) => s.name),
      outputs: (res.outputArguments || []).map((v) => v.value),
    };
  }
  if (action.do === "browse") {
    const res = await session.browse({
      nodeId: id(action.node),
      browseDirection: BrowseDirection.Forward,
      referenceTypeId: "HierarchicalReferences",
      includeSubtypes: true,
      resultMask: 63,
    });
    return { status: res.statusCode.name, names: res.references.map((r) => r.browseName.name) };
  }
  if (action.do === "processed") {
    return history(
      session,
      id(action.node),
      new ReadProcessedDetails({
        startTime: new Date(action.start),
        endTime: new Date(action.end),
        processingInterval: action.intervalMs,
        aggregateType: [id(action.aggregate)],
      }),
    );
  }
  if (action.do === "raw") {
    const res = await session.readHistoryValue({ nodeId: id(action.node) }, new Date(action.start), new Date(action.end), {
      returnBounds: false,
    });
    return { status: res.statusCode.name };
  }
  throw new Error(`unknown action ${JSON.stringify(action)}`);
}

async function main() {
  const { client, session } = await open(cfg, "conditions", say);
  const ns = (await session.readNamespaceArray()).indexOf(cfg.namespace);
  const id = (s) => (s.startsWith("s:") ? `ns=${ns};s=${s.slice(2)}` : s);
  for (const action of cfg.actions) {
    out.results.push(await run(session, action, id));
    say(action.do);
  }
  await session.close();
  await client.disconnect();
  say("closed");
}

main()
  .then(() => {
    process.stdout.write(JSON.stringify(out) + "\n");
    process.exit(0);
  })
  .catch((err) => {
    out.error = String(err && err.stack ? err.stack : err);
    process.stdout.write(JSON.stringify(out) + "\n");
    process.exit(1);
  });
