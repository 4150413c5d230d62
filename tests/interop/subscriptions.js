// Subscriptions with node-opcua-client (not asyncua), for
// tests/interop/test_opcua_subscriptions_interop.py: monitored items with absolute and
// percent deadbands, items a deadband does not apply to, TimestampsToReturn on Read and on
// a monitored item, and the ServerTimestamp of a value that has not changed.
//
// node subscriptions.js '{"endpoint": ..., "namespace": ..., "items": [{"name": ...,
//     "tag": ..., "deadband": "absolute" | "percent" | null, "value": <number>,
//     "trigger": "Status" | "StatusValue" | ..., "timestamps": "Both" | "Source" | ...}], "ranges": [<tag>, ...], "user": ...,
//     "password": ..., "applicationUri": ..., "cert": ..., "key": ..., "pki": ...}'
//
// It talks with the test in lines: each of its own starts with "@@ " and is one JSON
// object. It says {"ready": ...} (the EURanges it read, each item's creation status), then
// waits for commands on stdin, one JSON object a line:
//   {"until": {<item>: <value>}}  collect notifications until each item's last value is
//                                 the one given, then say {"received": {<item>: [...]}}
//   {"read": <tag>}               read it with each TimestampsToReturn, say {"read": ...}
//   {"end": true}                 close and exit
"use strict";
const { open } = require("./client.js");
const readline = require("node:readline");
const { ReadRequest } = require("node-opcua-service-read");
const {
  AttributeIds,
  BrowseDirection,
  ClientMonitoredItem,
  DataChangeFilter,
  DataChangeTrigger,
  DataType,
  DeadbandType,
  TimestampsToReturn,
  resolveNodeId,
} = require("node-opcua-client");

const cfg = JSON.parse(process.argv[2]);
const WAIT_MS = 30000; // a notification never comes: the test fails on what did come
const say = (obj) => process.stdout.write("@@ " + JSON.stringify(obj) + "\n");

// A Variant's value as JSON: node-opcua holds an Int64 as [high, low] 32-bit words.
function plain(variant) {
  const v = variant.value;
  const wide = variant.dataType === DataType.Int64 || variant.dataType === DataType.UInt64;
  return wide && Array.isArray(v) ? v[0] * 4294967296 + v[1] : v;
}

// A DataValue as JSON: the value, its status, and which timestamps came, in ms since 1970
// (a JS Date holds ms; the test compares within a millisecond).
function sample(dv) {
  return {
    value: dv.value ? plain(dv.value) : null,
    status: dv.statusCode.name,
    source: dv.sourceTimestamp ? dv.sourceTimestamp.getTime() : null,
    server: dv.serverTimestamp ? dv.serverTimestamp.getTime() : null,
  };
}

async function euRange(session, nodeId) {
  const browsed = await session.browse({
    nodeId,
    referenceTypeId: "HasProperty",
    browseDirection: BrowseDirection.Forward,
    includeSubtypes: true,
    resultMask: 63,
  });
  const ref = (browsed.references || []).find((r) => r.browseName.name === "EURange");
  if (!ref) return null;
  const dv = await session.read({ nodeId: ref.nodeId, attributeId: AttributeIds.Value });
  const r = dv.value.value;
  return r ? { low: r.low, high: r.high } : null;
}

// A Read with the TimestampsToReturn given (session.read always asks for Both).
function readWith(session, nodeId, timestampsToReturn) {
  const request = new ReadRequest({
    maxAge: 0,
    nodesToRead: [{ nodeId: resolveNodeId(nodeId), attributeId: AttributeIds.Value }],
    timestampsToReturn,
  });
  return new Promise((resolve, reject) =>
    session.performMessageTransaction(request, (err, response) =>
      err ? reject(err) : resolve(response.results[0])
    )
  );
}

function filterOf(item) {
  if (!item.deadband && !item.trigger) return null;
  return new DataChangeFilter({
    trigger: DataChangeTrigger[item.trigger || "StatusValue"],
    deadbandType: !item.deadband
      ? DeadbandType.None
      : item.deadband === "percent"
        ? DeadbandType.Percent
        : DeadbandType.Absolute,
    deadbandValue: item.value || 0,
  });
}

function monitor(subscription, id, item, received) {
  return new Promise((resolve) => {
    const mi = ClientMonitoredItem.create(
      subscription,
      { nodeId: id(item.tag), attributeId: AttributeIds.Value },
      { samplingInterval: 0, discardOldest: true, queueSize: 10000, filter: filterOf(item) },
      TimestampsToReturn[item.timestamps || "Both"]
    );
    received[item.name] = [];
    mi.on("changed", (dv) => received[item.name].push(sample(dv)));
    mi.on("initialized", () => resolve(mi.statusCode.name));
    mi.on("err", () => resolve(mi.statusCode.name));
  });
}

async function main() {
  const { client, session } = await open(cfg, "subscriptions");
  const ns = (await session.readNamespaceArray()).indexOf(cfg.namespace);
  const id = (s) => `ns=${ns};s=${s}`;

  const ranges = {};
  for (const tag of cfg.ranges) ranges[tag] = await euRange(session, id(tag));

  const subscription = await session.createSubscription2({
    requestedPublishingInterval: 50,
    requestedLifetimeCount: 6000,
    requestedMaxKeepAliveCount: 20,
    maxNotificationsPerPublish: 0,
    publishingEnabled: true,
    priority: 1,
  });
  const received = {};
  const created = {};
  for (const item of cfg.items) created[item.name] = await monitor(subscription, id, item, received);
  say({ ready: true, ranges, created });

  const lines = readline.createInterface({ input: process.stdin });
  for await (const line of lines) {
    const cmd = JSON.parse(line);
    if (cmd.until) {
      const deadline = Date.now() + WAIT_MS;
      const done = () =>
        Object.entries(cmd.until).every(([name, v]) => {
          const got = received[name];
          return got.length > 0 && got[got.length - 1].value === v;
        });
      while (!done() && Date.now() < deadline) await new Promise((r) => setTimeout(r, 20));
      say({ received });
    } else if (cmd.read) {
      const out = {};
      for (const ttr of ["Source", "Server", "Both", "Neither"]) {
        out[ttr] = sample(await readWith(session, id(cmd.read), TimestampsToReturn[ttr]));
      }
      say({ read: out });
    } else if (cmd.end) {
      break;
    }
  }
  await subscription.terminate();
  await session.close();
  await client.disconnect();
}

main()
  .then(() => process.exit(0))
  .catch((err) => {
    say({ error: String(err && err.stack ? err.stack : err) });
    process.exit(1);
  });
