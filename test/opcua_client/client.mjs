// An independent OPC UA client (node-opcua) for packml_ros2's tests.
//
//   node client.mjs '<job as JSON>'      one job, or
//   node client.mjs --lines              one job per stdin line, one answer per stdout line
//                                        (after a first line {"ready": true}): loading
//                                        node-opcua takes seconds, a test pays it once
//
// job: {
//   "url": "opc.tcp://127.0.0.1:4840/",
//   "mode": "None" | "Sign" | "SignAndEncrypt",        (default None)
//   "policy": "Basic256Sha256",                          (when mode is not None)
//   "user": null | {"name": "...", "password": "..."} | {"certificate": "x.der", "key": "x.pem"},
//   "pki": "<folder for the client's own certificate>",
//   "steps": [ {"op": ...}, ... ]
// }
// Browse paths start at the Objects folder (at the Root folder with a leading "/"); each element is "<ns>:<name>" where ns is 0, "P"
// (http://opcfoundation.org/UA/PackML/) or "U" (the server's own namespace, NamespaceArray[1]):
//   "P:PackMLObjects/U:filler/P:BaseStateMachine/0:CurrentState/0:Number"
// Steps (each answers one JSON object, in order):
//   {"op": "endpoints"}                            the server's endpoints
//   {"op": "read", "path": P[, "attribute": "UserExecutable"]}   {nodeId, status, value[, dimensions]}
//   {"op": "browse", "path": P}                    the browse names below P
//   {"op": "call", "path": P, "args": [{"type": "Int32", "value": 1}, ...][, "object": P2]}
//        P is the method; its parent is the object (or P2). {status, diagnostics, outputs,
//        inputArgumentResults}. Structures:
//        {"type": "ExtensionObject", "dataType": "P:i=16", "array": true, "value": [{fields}]}
//   {"op": "wait", "path": P, "value": V, "timeout": ms}   a subscription until the value is V
//   {"op": "wait", "path": P, "until": "<JS expression of v (value) and s (status name)>"}
//        ... until the expression holds: {value, status, at (ms since the epoch), seen}
//   {"op": "write", "path": P, "value": {"type": "Int32", "value": 1}[, "attribute": "Value"]}
//        {status} of the node's write (a ServiceFault: {error})
//   {"op": "namespaces"}                           Server/Namespaces: uri, version, publication date
//   {"op": "watch", "path": P, "name": N}          a subscription that records every value of P for
//        the rest of the job, from the first notification on (answered once that arrived, so a
//        later step cannot change P unseen): {value, status}
//   {"op": "watched", "name": N, "until": "<JS expression of seen (the values so far)>"[, "timeout": ms]}
//        ... until the expression holds: {seen}
// Prints {"ok": true, "results": [...]} or {"ok": false, "error": "...", "results": [...]}.

import fs from "node:fs";
import readline from "node:readline";

// stdout carries the answers only: node-opcua's own messages go to stderr
console.log = console.info = console.warn = (...args) => console.error(...args);

const {
    AttributeIds,
    ClientMonitoredItem,
    ClientSubscription,
    DataType,
    LocalizedText,
    MessageSecurityMode,
    NodeId,
    OPCUAClient,
    SecurityPolicy,
    TimestampsToReturn,
    UserTokenType,
    Variant,
    VariantArrayType,
    coerceNodeId,
    makeBrowsePath,
} = await import("node-opcua-client");
const { OPCUACertificateManager } = await import("node-opcua-certificate-manager");
const { LocalKeyOperations, readCertificate, readPrivateKey } = await import("node-opcua-crypto");

const PACKML_URI = "http://opcfoundation.org/UA/PackML/";

function plain(value) {
    if (value === null || value === undefined) return null;
    if (typeof value === "bigint") return Number(value);
    if (ArrayBuffer.isView(value)) return Array.from(value, plain);
    if (Array.isArray(value)) return value.map(plain);
    if (value instanceof Date) return value.toISOString();
    if (value instanceof NodeId) return value.toString();
    if (value instanceof LocalizedText) return { text: value.text, locale: value.locale };
    if (typeof value === "object") {
        if (value.constructor && value.constructor.name === "QualifiedName") return `${value.namespaceIndex}:${value.name}`;
        // structures: the field names of the data type (node-opcua's properties are lowerCamelCase)
        const out = {};
        const fields = value.schema && value.schema.fields;
        if (fields) {
            for (const f of fields) out[f.originalName ?? f.name] = plain(value[f.name]);
        } else {
            for (const key of Object.keys(value)) out[key] = plain(value[key]);
        }
        return out;
    }
    return value;
}

function dataValueJson(dv) {
    const out = { status: dv.statusCode.name, value: dv.value ? plain(dv.value.value) : null };
    if (dv.value && dv.value.arrayType === VariantArrayType.Matrix) out.dimensions = dv.value.dimensions;
    if (dv.sourceTimestamp) out.sourceTimestamp = dv.sourceTimestamp.toISOString();
    return out;
}

const certificateManagers = new Map();

function certificateManager(folder) {
    if (!certificateManagers.has(folder)) {
        certificateManagers.set(
            folder,
            new OPCUACertificateManager({ rootFolder: folder, automaticallyAcceptUnknownCertificate: true }),
        );
    }
    return certificateManagers.get(folder);
}

async function runJob(job) {
    const results = [];
    const mode = MessageSecurityMode[job.mode ?? "None"];
    const policy = (job.mode ?? "None") === "None" ? SecurityPolicy.None : SecurityPolicy[job.policy ?? "Basic256Sha256"];
    const client = OPCUAClient.create({
        applicationName: "packml_ros2 test client (node-opcua)",
        applicationUri: "urn:packml_ros2:test-client",
        clientCertificateManager: certificateManager(job.pki),
        securityMode: mode,
        securityPolicy: policy,
        endpointMustExist: false,
        keepSessionAlive: false,
        connectionStrategy: { maxRetry: 3, initialDelay: 200, maxDelay: 1000 },
        requestedSessionTimeout: 60000,
    });
    let session = null;
    const watches = new Map(); // name -> {subscription, seen, changed}
    try {
        await client.connect(job.url);
        let identity = undefined;
        if (job.user && job.user.name) {
            identity = { type: UserTokenType.UserName, userName: job.user.name, password: job.user.password };
        } else if (job.user && job.user.certificate) {
            identity = {
                type: UserTokenType.Certificate,
                certificateData: readCertificate(job.user.certificate),
                keyOperations: new LocalKeyOperations(readPrivateKey(job.user.key)),
            };
        }
        try {
            session = await client.createSession(identity);
        } catch (err) {
            return { ok: false, error: `session: ${err.message}`, results };
        }
        const namespaces = await session.readNamespaceArray();
        const alias = { 0: 0, P: namespaces.indexOf(PACKML_URI), U: 1 };
        const resolve = async (path) => {
            const root = path.startsWith("/") ? "i=84" : "i=85"; // "/...": from the Root folder
            const text = path
                .replace(/^\//, "")
                .split("/")
                .map((part) => {
                    const i = part.indexOf(":");
                    return `/${alias[part.slice(0, i)]}:${part.slice(i + 1)}`;
                })
                .join("");
            const res = await session.translateBrowsePath(makeBrowsePath(root, text));
            if (!res.targets || res.targets.length === 0) throw new Error(`no node at ${path} (${res.statusCode.name})`);
            return res.targets[0].targetId;
        };
        for (const step of job.steps) {
            const t0 = Date.now();
            try {
                results.push({ ...(await run(session, step, resolve, client, alias, watches)), ms: Date.now() - t0 });
            } catch (err) {
                results.push({ error: err.message, ms: Date.now() - t0 });
            }
        }
        return { ok: true, results };
    } catch (err) {
        return { ok: false, error: err.message, results };
    } finally {
        for (const w of watches.values()) await w.subscription.terminate().catch(() => {});
        if (session) await session.close().catch(() => {});
        await client.disconnect().catch(() => {});
    }
}

async function argument(session, arg, alias) {
    // "P:i=16": a NodeId in the PackML namespace, whatever its index
    const nodeId = (text) => coerceNodeId(text.startsWith("P:") ? `ns=${alias.P};${text.slice(2)}` : text);
    if (arg.type === "NodeId") return new Variant({ dataType: DataType.NodeId, value: nodeId(arg.value) });
    if (arg.type === "ExtensionObject") {
        const dataType = nodeId(arg.dataType);
        const values = [];
        for (const fields of arg.array ? arg.value : [arg.value]) {
            values.push(await session.constructExtensionObject(dataType, fields));
        }
        return new Variant({
            dataType: DataType.ExtensionObject,
            arrayType: arg.array ? VariantArrayType.Array : VariantArrayType.Scalar,
            value: arg.array ? values : values[0],
        });
    }
    return new Variant({ dataType: DataType[arg.type], value: arg.value });
}

function subscribe(session) {
    return ClientSubscription.create(session, {
        requestedPublishingInterval: 50,
        requestedLifetimeCount: 1000,
        requestedMaxKeepAliveCount: 20,
        publishingEnabled: true,
    });
}

async function run(session, step, resolve, client, alias, watches) {
    switch (step.op) {
        case "watch": {
            const nodeId = await resolve(step.path);
            const w = { subscription: subscribe(session), seen: [], changed: () => {} };
            watches.set(step.name, w);
            return await new Promise((resolvePromise, reject) => {
                const timer = setTimeout(() => reject(new Error(`no value of ${step.path}`)), step.timeout ?? 10000);
                const item = ClientMonitoredItem.create(
                    w.subscription,
                    { nodeId, attributeId: AttributeIds.Value },
                    { samplingInterval: 0, discardOldest: false, queueSize: 1000 },
                    TimestampsToReturn.Both,
                );
                item.on("changed", (dv) => {
                    const value = plain(dv.value ? dv.value.value : null);
                    w.seen.push(value);
                    w.changed();
                    if (w.seen.length === 1) {
                        clearTimeout(timer);
                        resolvePromise({ value, status: dv.statusCode.name });
                    }
                });
                item.on("err", (message) => {
                    clearTimeout(timer);
                    reject(new Error(message));
                });
            });
        }
        case "watched": {
            const w = watches.get(step.name);
            if (!w) throw new Error(`no watch ${step.name}`);
            const until = new Function("seen", `return (${step.until});`);
            const holds = () => {
                try {
                    return Boolean(until(w.seen));
                } catch {
                    return false;
                }
            };
            return await new Promise((resolvePromise, reject) => {
                const timer = setTimeout(() => {
                    w.changed = () => {};
                    reject(new Error(`timeout waiting for ${step.until} of ${step.name}; seen ${JSON.stringify(w.seen.slice(-10))}`));
                }, step.timeout ?? 10000);
                w.changed = () => {
                    if (holds()) {
                        clearTimeout(timer);
                        w.changed = () => {};
                        resolvePromise({ seen: w.seen });
                    }
                };
                w.changed();
            });
        }
        case "endpoints": {
            const endpoints = await client.getEndpoints();
            return {
                endpoints: endpoints.map((e) => ({
                    url: e.endpointUrl,
                    mode: MessageSecurityMode[e.securityMode],
                    policy: e.securityPolicyUri,
                    tokens: (e.userIdentityTokens || []).map((t) => UserTokenType[t.tokenType]),
                })),
            };
        }
        case "read": {
            const nodeId = await resolve(step.path);
            const attributeId = AttributeIds[step.attribute ?? "Value"];
            return { nodeId: nodeId.toString(), ...dataValueJson(await session.read({ nodeId, attributeId })) };
        }
        case "namespaces": {
            const folder = await resolve("/0:Objects/0:Server/0:Namespaces");
            const out = [];
            for (const ref of (await session.browse(folder)).references) {
                const field = async (name) => {
                    const res = await session.translateBrowsePath(makeBrowsePath(ref.nodeId, `/0:${name}`));
                    if (!res.targets || res.targets.length === 0) return null;
                    return plain((await session.read({ nodeId: res.targets[0].targetId, attributeId: AttributeIds.Value })).value.value);
                };
                out.push({
                    uri: await field("NamespaceUri"),
                    version: await field("NamespaceVersion"),
                    publicationDate: await field("NamespacePublicationDate"),
                });
            }
            return { namespaces: out };
        }
        case "browse": {
            const nodeId = await resolve(step.path);
            const res = await session.browse(nodeId);
            return { names: res.references.map((r) => `${r.browseName.namespaceIndex}:${r.browseName.name}`) };
        }
        case "call": {
            const methodId = await resolve(step.path);
            const objectId = await resolve(step.object ?? step.path.split("/").slice(0, -1).join("/"));
            const inputArguments = [];
            for (const arg of step.args || []) inputArguments.push(await argument(session, arg, alias));
            // operation level: SymbolicId | LocalizedText | AdditionalInfo
            const { results, diagnosticInfos, diagnosticStrings } = await session.callWithDiagnostics(
                [{ objectId, methodId, inputArguments }],
                0x20 | 0x40 | 0x80,
            );
            const r = results[0];
            const d = diagnosticInfos[0];
            return {
                status: r.statusCode.name,
                good: r.statusCode.isGood(),
                diagnostics: d
                    ? {
                          additionalInfo: d.additionalInfo ?? null,
                          localizedText: diagnosticStrings[0].localizedText,
                          symbolicId: diagnosticStrings[0].symbolicId,
                      }
                    : null,
                outputs: (r.outputArguments || []).map((v) => plain(v.value)),
                inputArgumentResults: (r.inputArgumentResults || []).map((c) => c.name),
            };
        }
        case "write": {
            // a ServiceFault throws: the step answers {error}; a per-node refusal is {status}
            const nodeId = await resolve(step.path);
            const value = await argument(session, step.value, alias);
            const attributeId = AttributeIds[step.attribute ?? "Value"];
            const status = await session.write({ nodeId, attributeId, value: { value } });
            return { status: status.name };
        }
        case "wait": {
            const nodeId = await resolve(step.path);
            const want = JSON.stringify(step.value);
            const until = step.until ? new Function("v", "s", `return (${step.until});`) : (v) => JSON.stringify(v) === want;
            const subscription = subscribe(session);
            const seen = [];
            try {
                return await new Promise((resolvePromise, reject) => {
                    const timer = setTimeout(
                        () => reject(new Error(`timeout waiting for ${step.until ?? want} at ${step.path}; seen ${JSON.stringify(seen.slice(-5))}`)),
                        step.timeout ?? 10000,
                    );
                    const item = ClientMonitoredItem.create(
                        subscription,
                        { nodeId, attributeId: AttributeIds.Value },
                        { samplingInterval: 0, discardOldest: true, queueSize: 100 },
                        TimestampsToReturn.Both,
                    );
                    item.on("changed", (dv) => {
                        const at = Date.now();
                        const value = plain(dv.value ? dv.value.value : null);
                        const status = dv.statusCode.name;
                        seen.push(value);
                        let done = false;
                        try {
                            done = Boolean(until(value, status));
                        } catch {
                            done = false;
                        }
                        if (done) {
                            clearTimeout(timer);
                            resolvePromise({ value, status, at, seen });
                        }
                    });
                    item.on("err", (message) => {
                        clearTimeout(timer);
                        reject(new Error(message));
                    });
                });
            } finally {
                await subscription.terminate().catch(() => {});
            }
        }
        default:
            throw new Error(`unknown op ${step.op}`);
    }
}

if (process.argv[2] === "--lines") {
    process.stdout.write(JSON.stringify({ ready: true }) + "\n");
    const lines = readline.createInterface({ input: process.stdin });
    for await (const line of lines) {
        if (!line.trim()) continue;
        let outcome;
        try {
            outcome = await runJob(JSON.parse(line));
        } catch (err) {
            outcome = { ok: false, error: err.message, results: [] };
        }
        process.stdout.write(JSON.stringify(outcome) + "\n");
    }
} else {
    const outcome = await runJob(JSON.parse(process.argv[2] ?? fs.readFileSync(0, "utf8")));
    process.stdout.write(JSON.stringify(outcome) + "\n");
}
process.exit(0);
