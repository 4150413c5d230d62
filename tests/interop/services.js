// OPC UA sessions, security and service limits as an integrator's node-opcua client meets
// them (issue 31, findings 1 and 4), for tests/interop/test_opcua_services_interop.py. One
// JSON line of what it saw on stdout, then it exits.
//
// node services.js '{"check": ..., "endpoint": ..., "namespace": ..., "cert": ..., "key": ...,
//                    "pki": ..., "applicationUri": ..., ...}'
//
// checks:
//   none-untrusted  the None endpoint with a certificate nobody trusted: a session, a read
//   secure-untrusted  SignAndEncrypt with that certificate, `tries` times: each refused
//   limits          the advertised OperationLimits, one Read/Browse/... past them, Browse
//                   with requestedMaxReferencesPerNode=1 and BrowseNext to the end
//   browse-load     browses `nodes` nodes in a loop for `seconds` (says "browsing" on stderr
//                   when it starts)
//   watch           a 100 ms subscription's longest gap between notifications over
//                   `seconds`; a fresh client connects meanwhile
"use strict";
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
const {
  OPCUAClient,
  MessageSecurityMode,
  SecurityPolicy,
  AttributeIds,
  BrowseDirection,
  DataType,
  TimestampsToReturn,
  UserTokenType,
} = require("node-opcua-client");

const cfg = JSON.parse(process.argv[2]);
const out = {};
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

function makeClient(secure, name) {
  return OPCUAClient.create({
    applicationName: `bench-supervisor services ${name}`,
    applicationUri: cfg.applicationUri,
    securityMode: secure ? MessageSecurityMode.SignAndEncrypt : MessageSecurityMode.None,
    securityPolicy: secure ? SecurityPolicy.Basic256Sha256 : SecurityPolicy.None,
    certificateFile: cfg.cert,
    privateKeyFile: cfg.key,
    clientCertificateManager: new OPCUACertificateManager({
      rootFolder: `${cfg.pki}-${name}`,
      automaticallyAcceptUnknownCertificate: true,
    }),
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 200 },
    requestedSessionTimeout: 120000,
  });
}

async function open(secure, name) {
  const client = makeClient(secure, name);
  await client.connect(cfg.endpoint);
  const session = await client.createSession({ type: UserTokenType.Anonymous });
  const ns = (await session.readNamespaceArray()).indexOf(cfg.namespace);
  return { client, session, ns, id: (s) => `ns=${ns};s=${s}` };
}

async function close({ client, session }) {
  await session.close();
  await client.disconnect();
}

const status = (err) => {
  const m = /Bad[A-Za-z]+/.exec(String(err && err.message ? err.message : err));
  return m ? m[0] : String(err);
};

async function noneUntrusted() {
  const c = await open(false, "none");
  const dv = await c.session.read({ nodeId: c.id("ch0.voltage"), attributeId: AttributeIds.Value });
  out.read = dv.statusCode.name;
  await close(c);
}

async function secureUntrusted() {
  out.tries = [];
  for (let i = 0; i < cfg.tries; i++) {
    const client = makeClient(true, `secure${i}`);
    try {
      await client.connect(cfg.endpoint);
      const session = await client.createSession({ type: UserTokenType.Anonymous });
      out.tries.push("Good");
      await session.close();
    } catch (err) {
      out.tries.push(status(err));
    } finally {
      await client.disconnect();
    }
  }
}

const LIMITS = [
  "MaxNodesPerRead",
  "MaxNodesPerWrite",
  "MaxNodesPerBrowse",
  "MaxNodesPerMethodCall",
  "MaxNodesPerTranslateBrowsePathsToNodeIds",
  "MaxNodesPerRegisterNodes",
  "MaxMonitoredItemsPerCall",
  "MaxNodesPerHistoryReadData",
];

function refs(result) {
  return (result.references || []).map((r) => `${r.isForward ? ">" : "<"}${r.referenceTypeId}:${r.nodeId}`);
}

async function limits() {
  const c = await open(false, "limits");
  const { session, id } = c;
  const caps = await session.browse("ns=0;i=11704"); // ServerCapabilities/OperationLimits
  const byName = {};
  for (const r of caps.references) byName[r.browseName.name] = r.nodeId;
  out.limits = {};
  for (const name of LIMITS) {
    const dv = await session.read({ nodeId: byName[name], attributeId: AttributeIds.Value });
    out.limits[name] = dv.value.value;
  }
  const maxRead = out.limits.MaxNodesPerRead;
  const unknown = (n) => Array.from({ length: n }, (_, i) => ({ nodeId: `ns=${c.ns};s=no.such.${i}`, attributeId: AttributeIds.Value }));
  try {
    const dvs = await session.read(unknown(maxRead + 1));
    out.readPast = `served ${dvs.length}`;
  } catch (err) {
    out.readPast = status(err);
  }
  const atLimit = await session.read(unknown(maxRead));
  out.readAt = { count: atLimit.length, first: atLimit[0].statusCode.name };
  const maxBrowse = out.limits.MaxNodesPerBrowse;
  try {
    const rs = await session.browse(Array.from({ length: maxBrowse + 1 }, () => id("/Bench")));
    out.browsePast = `served ${rs.length}`;
  } catch (err) {
    out.browsePast = status(err);
  }
  const maxWrite = out.limits.MaxNodesPerWrite;
  try {
    const writes = Array.from({ length: maxWrite + 1 }, () => ({
      nodeId: id("ch0.manual_current"),
      attributeId: AttributeIds.Value,
      value: { value: { dataType: DataType.Double, value: 0.0 } },
    }));
    const rs = await session.write(writes);
    out.writePast = `served ${rs.length}`;
  } catch (err) {
    out.writePast = status(err);
  }
  const maxCall = out.limits.MaxNodesPerMethodCall;
  try {
    const calls = Array.from({ length: maxCall + 1 }, () => ({
      objectId: id("/Bench/Channels/ch0"),
      methodId: id("/Bench/Channels/ch0/Hold"),
      inputArguments: [],
    }));
    const rs = await session.call(calls);
    out.callPast = `served ${rs.length}`;
  } catch (err) {
    out.callPast = status(err);
  }

  // One reference at a time: the same references as one plain browse, in order.
  const what = { nodeId: id("ch0.voltage"), browseDirection: BrowseDirection.Both, referenceTypeId: "References", includeSubtypes: true, resultMask: 63 };
  session.requestedMaxReferencesPerNode = 0;
  const [whole] = await session.browse([what]);
  out.whole = refs(whole);
  session.requestedMaxReferencesPerNode = 1;
  const [first] = await session.browse([what]);
  out.first = { status: first.statusCode.name, count: first.references.length, more: !!(first.continuationPoint && first.continuationPoint.length) };
  const paged = refs(first);
  let cp = first.continuationPoint;
  out.nextStatuses = [];
  while (cp && cp.length) {
    const [next] = await session.browseNext([cp], false);
    out.nextStatuses.push(next.statusCode.name);
    paged.push(...refs(next));
    cp = next.continuationPoint;
    if (out.nextStatuses.length > 200) break;
  }
  out.paged = paged;
  // A released continuation point is gone.
  const [again] = await session.browse([what]);
  const [released] = await session.browseNext([again.continuationPoint], true);
  out.released = released.statusCode.name;
  const [stale] = await session.browseNext([again.continuationPoint], false);
  out.stale = stale.statusCode.name;
  session.requestedMaxReferencesPerNode = 0;
  await close(c);
}

async function collectNodes(session, start) {
  const seen = new Set([start]);
  let frontier = [start];
  while (frontier.length) {
    const rs = await session.browse(
      frontier.map((n) => ({ nodeId: n, browseDirection: BrowseDirection.Forward, referenceTypeId: "HierarchicalReferences", includeSubtypes: true, resultMask: 63 })),
    );
    const next = [];
    for (const r of rs)
      for (const ref of r.references || []) {
        const s = ref.nodeId.toString();
        if (!seen.has(s)) {
          seen.add(s);
          next.push(s);
        }
      }
    frontier = next;
  }
  return [...seen];
}

// The browsing client: in a process of its own (decoding megabytes of answers holds a
// node process's one thread: a watcher in the same process would time its own stalls).
async function browseLoad() {
  const browser = await open(false, "browser");
  // The whole address space, as an integrator's tag browser walks it; then `nodes` browses
  // of those with `minRefs` to `maxRefs` references (the standard types: asyncua took
  // 0.2 ms a reference there, 34 s for 10,000 such nodes), both directions, every reference
  // type.
  const all = await collectNodes(browser.session, "ns=0;i=84");
  const both = (nodeId) => ({
    nodeId,
    browseDirection: BrowseDirection.Both,
    referenceTypeId: "References",
    includeSubtypes: true,
    resultMask: 63,
  });
  const nodes = [];
  for (let i = 0; i < all.length; i += 500) {
    const rs = await browser.session.browse(all.slice(i, i + 500).map(both));
    rs.forEach((r, k) => {
      const n = (r.references || []).length;
      if (n >= cfg.minRefs && n <= cfg.maxRefs) nodes.push(all[i + k]);
    });
  }
  out.distinctNodes = nodes.length;
  const many = Array.from({ length: cfg.nodes }, (_, i) => both(nodes[i % nodes.length]));
  browser.session.requestedMaxReferencesPerNode = 0;
  process.stderr.write("browsing\n"); // the test starts the watcher now
  out.browses = [];
  const until = Date.now() + cfg.seconds * 1000;
  while (Date.now() < until || out.browses.length < cfg.minBrowses) {
    const t0 = Date.now();
    const rs = await browser.session.browse(many);
    out.browses.push({ ms: Date.now() - t0, results: rs.length, refs: rs.reduce((n, r) => n + (r.references || []).length, 0) });
  }
  await close(browser);
}

// The watched client: a 100 ms subscription, its longest gap between notifications while
// the other process browses; a fresh client connects meanwhile.
async function watch() {
  const watcher = await open(false, "watcher");
  const sub = await watcher.session.createSubscription2({
    requestedPublishingInterval: cfg.intervalMs,
    requestedMaxKeepAliveCount: 10,
    requestedLifetimeCount: 1000,
    publishingEnabled: true,
  });
  out.revisedIntervalMs = sub.publishingInterval;
  const times = [];
  const item = await sub.monitor(
    { nodeId: watcher.id("scan.count"), attributeId: AttributeIds.Value },
    { samplingInterval: cfg.intervalMs, queueSize: 10, discardOldest: true },
    TimestampsToReturn.Both,
  );
  item.on("changed", () => times.push(Date.now()));
  await sleep(1000); // the first notifications (the initial value) are not timed
  const start = Date.now();
  await sleep(cfg.seconds * 500);
  const t0 = Date.now();
  const fresh = await open(false, "fresh");
  await fresh.session.read({ nodeId: fresh.id("scan.count"), attributeId: AttributeIds.Value });
  out.freshConnectMs = Date.now() - t0;
  await close(fresh);
  await sleep(Math.max(0, start + cfg.seconds * 1000 - Date.now()));
  const end = Date.now();
  const during = times.filter((t) => t >= start && t <= end);
  const marks = [start, ...during, end];
  let longest = 0;
  for (let i = 1; i < marks.length; i++) longest = Math.max(longest, marks[i] - marks[i - 1]);
  out.notifications = during.length;
  out.watchedMs = end - start;
  out.longestGapMs = longest;
  await close(watcher);
}

const checks = { "none-untrusted": noneUntrusted, "secure-untrusted": secureUntrusted, limits, "browse-load": browseLoad, watch };

checks[cfg.check]()
  .then(() => {
    process.stdout.write(JSON.stringify(out) + "\n");
    process.exit(0);
  })
  .catch((err) => {
    out.error = String(err && err.stack ? err.stack : err);
    process.stdout.write(JSON.stringify(out) + "\n");
    process.exit(1);
  });
