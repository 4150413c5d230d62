// HistoryRead raw with node-opcua-client (not asyncua), for tests/interop/test_history_interop.py:
// it reads the raw history of a historised tag from the supervisor's server in one answer
// and again in pages of 7 (continuation points), asks the same of a tag that is not
// historised, then prints one JSON line of what it got and exits.
//
// node history.js '{"endpoint": ..., "namespace": ..., "tag": ..., "notKept": ...,
//                   "start": <ms since 1970>, "end": <ms>, "user": ..., "password": ...,
//                   "secure": false, "applicationUri": ..., "cert": ..., "key": ..., "pki": ...}'
"use strict";
const { open } = require("./client.js");
const {
  TimestampsToReturn,
} = require("node-opcua-client");

const cfg = JSON.parse(process.argv[2]);
const out = { steps: [] };
const say = (step) => out.steps.push(step);

// A DataValue as JSON: the value, its status, and its source time in seconds since 1970 to
// the 100 ns of OPC UA's DateTime (a JS Date holds ms; node-opcua keeps the rest in
// sourcePicoseconds).
function sample(dv) {
  const t = dv.sourceTimestamp;
  return {
    value: dv.value ? dv.value.value : null,
    status: dv.statusCode.name,
    source: t ? t.getTime() / 1000 + (dv.sourcePicoseconds || 0) * 1e-12 : null,
  };
}

async function raw(session, nodeId, options, continuationPoint) {
  const start = new Date(cfg.start);
  const end = new Date(cfg.end);
  const result = await session.readHistoryValue({ nodeId, continuationPoint }, start, end, {
    returnBounds: false, // node-opcua asks for bounding values unless told otherwise
    timestampsToReturn: TimestampsToReturn.Source,
    ...options,
  });
  const values = result.historyData && result.historyData.dataValues ? result.historyData.dataValues : [];
  return {
    status: result.statusCode.name,
    values: values.map(sample),
    continuationPoint: result.continuationPoint && result.continuationPoint.length ? result.continuationPoint : null,
  };
}

async function main() {
  const { client, session } = await open(cfg, "history", say, cfg.secure);
  const ns = (await session.readNamespaceArray()).indexOf(cfg.namespace);
  const id = (s) => `ns=${ns};s=${s}`;

  const whole = await raw(session, id(cfg.tag), {});
  out.whole = { status: whole.status, values: whole.values, more: whole.continuationPoint !== null };
  say("raw");

  const pages = [];
  let cp;
  for (;;) {
    const page = await raw(session, id(cfg.tag), { numValuesPerNode: 7 }, cp);
    pages.push({ status: page.status, values: page.values });
    cp = page.continuationPoint;
    if (!cp || pages.length > 1000) break;
  }
  out.pages = pages;
  say("paged");

  const other = await raw(session, id(cfg.notKept), {});
  out.notKept = { status: other.status, count: other.values.length };
  say("not kept");

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
