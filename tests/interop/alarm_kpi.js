// An integrator's node-opcua client (not asyncua) reads the alarm KPI tags, for
// tests/interop/test_alarm_kpi_interop.py: one session, one Read of every node named, one
// JSON line {"values": {tag: value}, "status": {tag: name}} printed, then it exits.
//
// node alarm_kpi.js '{"endpoint": ..., "namespace": ..., "tags": [...], "user": ...,
//                     "password": ..., "applicationUri": ..., "cert": ..., "key": ..., "pki": ...}'
"use strict";
const { open } = require("./client.js");
const { AttributeIds } = require("node-opcua-client");

const cfg = JSON.parse(process.argv[2]);
// Int64 (the project's integer tags) comes as [high, low] 32-bit words in node-opcua.
const plain = (v) => (Array.isArray(v) ? v[0] * 2 ** 32 + v[1] : v);

(async () => {
  const { client, session } = await open(cfg, "alarm kpi");
  let result;
  try {
    const ns = (await session.readNamespaceArray()).indexOf(cfg.namespace);
    const read = await session.read(
      cfg.tags.map((t) => ({ nodeId: `ns=${ns};s=${t}`, attributeId: AttributeIds.Value })),
    );
    const values = {};
    const status = {};
    cfg.tags.forEach((t, i) => {
      values[t] = plain(read[i].value.value);
      status[t] = read[i].statusCode.name;
    });
    result = { values, status };
  } finally {
    await session.close();
    await client.disconnect();
  }
  console.log(JSON.stringify(result)); // last: after node-opcua's own lines
})().catch((err) => {
  console.log(JSON.stringify({ error: String(err) }));
  process.exit(1);
});
