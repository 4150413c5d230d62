// The node-opcua-client connection every interop script opens the same way: its own
// certificate store (unknown server certificates accepted: the tests decide trust on the
// server's side), None or SignAndEncrypt with Basic256Sha256, a user name and password.
"use strict";
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
const { OPCUAClient, MessageSecurityMode, SecurityPolicy, UserTokenType } = require("node-opcua-client");

// A connected client and its session; `say("connected")` and `say("session")` on the way.
// cfg: {endpoint, applicationUri, cert, key, pki, user, password}.
async function open(cfg, name, say = () => {}, secure = false) {
  const client = OPCUAClient.create({
    applicationName: `bench-supervisor interop ${name}`.trim(),
    applicationUri: cfg.applicationUri,
    securityMode: secure ? MessageSecurityMode.SignAndEncrypt : MessageSecurityMode.None,
    securityPolicy: secure ? SecurityPolicy.Basic256Sha256 : SecurityPolicy.None,
    certificateFile: cfg.cert,
    privateKeyFile: cfg.key,
    clientCertificateManager: new OPCUACertificateManager({
      rootFolder: cfg.pki,
      automaticallyAcceptUnknownCertificate: true,
    }),
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 2, initialDelay: 200, maxDelay: 1000 },
  });
  await client.connect(cfg.endpoint);
  say("connected");
  const session = await client.createSession({
    type: UserTokenType.UserName,
    userName: cfg.user,
    password: cfg.password,
  });
  say("session");
  return { client, session };
}

module.exports = { open };
