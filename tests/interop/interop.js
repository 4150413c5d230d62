// An OPC UA client that is not asyncua (node-opcua-client), for
// tests/integration/test_opcua_interop.py: it browses the bench, reads a value with its
// EU and EURange, subscribes, calls Start, receives a step event and (ConditionRefresh) an
// alarm condition, then prints one JSON line of what it saw and exits.
//
// node interop.js '{"endpoint": ..., "namespace": ..., "recipe": ..., "user": ...,
//                   "password": ..., "secure": false, "cert": ..., "key": ..., "pki": ...}'
"use strict";
const { open } = require("./client.js");
const {
  AttributeIds,
  DataType,
  TimestampsToReturn,
  constructEventFilter,
} = require("node-opcua-client");

const cfg = JSON.parse(process.argv[2]);
const out = { steps: [] };
const say = (step) => out.steps.push(step);
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

async function until(what, cond, ms) {
  const t0 = Date.now();
  while (!cond()) {
    if (Date.now() - t0 > ms) throw new Error(`gave up waiting for ${what}`);
    await sleep(50);
  }
}

async function main() {
  const { client, session } = await open(cfg, "", say, cfg.secure);
  const nsArray = (await session.readNamespaceArray());
  const ns = nsArray.indexOf(cfg.namespace);
  out.namespaceIndex = ns;
  const id = (s) => `ns=${ns};s=${s}`;

  const channels = await session.browse(id("/Bench/Channels"));
  out.channels = channels.references.map((r) => r.browseName.name);

  const voltage = await session.read({ nodeId: id("ch0.voltage"), attributeId: AttributeIds.Value });
  out.voltage = { value: voltage.value.value, status: voltage.statusCode.name };
  const children = await session.browse(id("ch0.voltage"));
  const byName = {};
  for (const r of children.references) byName[r.browseName.name] = r.nodeId.toString();
  const range = await session.read({ nodeId: byName.EURange, attributeId: AttributeIds.Value });
  out.euRange = { low: range.value.value.low, high: range.value.value.high };
  const eu = await session.read({ nodeId: byName.EngineeringUnits, attributeId: AttributeIds.Value });
  out.engineeringUnits = {
    unitId: eu.value.value.unitId,
    displayName: eu.value.value.displayName.text,
    namespaceUri: eu.value.value.namespaceUri,
  };
  const typeDef = await session.browse({
    nodeId: id("ch0.voltage"),
    referenceTypeId: "HasTypeDefinition",
  });
  out.typeDefinition = typeDef.references.map((r) => r.nodeId.toString());
  say("read");

  const subscription = await session.createSubscription2({
    requestedPublishingInterval: 50,
    requestedMaxKeepAliveCount: 20,
    requestedLifetimeCount: 600,
    publishingEnabled: true,
  });
  const counts = [];
  const item = await subscription.monitor(
    { nodeId: id("scan.count"), attributeId: AttributeIds.Value },
    { samplingInterval: 50, queueSize: 10, discardOldest: true },
    TimestampsToReturn.Both,
  );
  // Int64 (the project's integer tags) comes as [high, low] 32-bit words in node-opcua.
  const int64 = (v) => (Array.isArray(v) ? v[0] * 2 ** 32 + v[1] : Number(v));
  item.on("changed", (dv) => counts.push(int64(dv.value.value)));
  const fields = ["EventType", "SourceName", "Message", "Severity", "ConditionName", "Retain"];
  const events = [];
  const eventItem = await subscription.monitor(
    { nodeId: "ns=0;i=2253", attributeId: AttributeIds.EventNotifier },
    { queueSize: 100, filter: constructEventFilter(fields) },
    TimestampsToReturn.Both,
  );
  eventItem.on("changed", (values) => {
    const e = {};
    fields.forEach((f, k) => {
      const v = values[k].value;
      if (v === null || typeof v === "number" || typeof v === "boolean") e[f] = v;
      else if (v.text !== undefined) e[f] = v.text; // LocalizedText
      else e[f] = v.toString(); // NodeId, String
    });
    events.push(e);
  });
  say("subscribed");

  const call = await session.call({
    objectId: id("/Bench/Channels/ch0"),
    methodId: id("/Bench/Channels/ch0/Start"),
    inputArguments: [
      { dataType: DataType.String, value: cfg.recipe },
      { dataType: DataType.String, value: "" },
    ],
  });
  out.start = { status: call.statusCode.name, result: call.outputArguments[0].value };
  const refused = await session.call({
    objectId: id("/Bench/Channels/ch0"),
    methodId: id("/Bench/Channels/ch0/SetManualCurrent"),
    inputArguments: [{ dataType: DataType.String, value: "0.3" }],
  });
  out.refused = {
    status: refused.statusCode.name,
    result: refused.outputArguments.length ? refused.outputArguments[0].value : null,
  };
  say("called");
  await until("a step event", () => events.some((e) => /^starting step/.test(e.Message)), 20000);
  const refresh = await session.call({
    objectId: "ns=0;i=2782", // ConditionType
    methodId: "ns=0;i=3875", // ConditionType.ConditionRefresh
    inputArguments: [{ dataType: DataType.UInt32, value: subscription.subscriptionId }],
  });
  out.refresh = refresh.statusCode.name;
  await until("an alarm condition", () => events.some((e) => e.ConditionName), 20000);
  await until("three updates", () => counts.length >= 3, 20000);
  out.counts = counts;
  out.events = events;
  await subscription.terminate();
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
