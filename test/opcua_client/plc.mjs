// A PackML machine as a PLC exposes it, for packml_ros2's PLC bridge tests: an OPC UA server of
// another implementation (node-opcua) that loads the official OPC 30050 NodeSet
// (node-opcua-nodesets), instantiates one PackMLBaseObjectType under PackMLObjects and runs its
// own small TR88-2022 state machine. Nothing of packml_ros2 is used.
//
//   node plc.mjs '<options as JSON>'
//
// options: {"port": 4850, "unit": "wrapper", "dwell": 150 (ms in each acting state),
//           "users": {"name": "password"} (then anonymous sessions are refused),
//           "secure": false (true: Basic256Sha256 Sign/SignAndEncrypt only), "pki": "<folder>",
//           "rate": 10 (pieces per second in Execute)}
// stdout: one JSON line {"ready": true, "endpoint": "..."} once the server listens, then one JSON
// line per transition {"state": N, "name": "EXECUTE", "cause": "Start"}.
// stdin, one JSON object per line:
//   {"fault": {"id": 3001, "value": 0, "message": "Film break", "category": 2, "reaction": "stop"}}
//        an alarm (active, unacknowledged) that becomes the StopReason and stops (or aborts) the
//        machine; Reset is refused (BadInvalidState) while it is active
//   {"clear": true}       the alarm's condition goes away
//   {"blocked": true}     Status/EquipmentBlocked (likewise "starved")
//   {"command": "Stop"}   a command given at the machine itself (its panel)

import fs from "node:fs";
import readline from "node:readline";
import { createRequire } from "node:module";

console.log = console.info = console.warn = (...args) => console.error(...args);
const out = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");

const require = createRequire(import.meta.url);
const { nodesets } = require("node-opcua-nodesets");
const { OPCUAServer } = await import("node-opcua-server");
const {
    DataType, LocalizedText, MessageSecurityMode, NodeId, SecurityPolicy, StatusCodes, Variant, VariantArrayType,
} = await import("node-opcua-client");
const { OPCUACertificateManager } = await import("node-opcua-certificate-manager");

const options = JSON.parse(process.argv[2] ?? "{}");
const PACKML_URI = "http://opcfoundation.org/UA/PackML/";
const dwell = options.dwell ?? 150;

// TR88 state numbers and the TR88-2022 table
const N = { CLEARING: 1, STOPPED: 2, STARTING: 3, IDLE: 4, SUSPENDED: 5, EXECUTE: 6, STOPPING: 7, ABORTING: 8,
            ABORTED: 9, HOLDING: 10, HELD: 11, UNHOLDING: 12, SUSPENDING: 13, UNSUSPENDING: 14, RESETTING: 15,
            COMPLETING: 16, COMPLETE: 17 };
const NAME = Object.fromEntries(Object.entries(N).map(([k, v]) => [v, k]));
const SC = { [N.RESETTING]: N.IDLE, [N.STARTING]: N.EXECUTE, [N.COMPLETING]: N.COMPLETE, [N.HOLDING]: N.HELD,
             [N.UNHOLDING]: N.EXECUTE, [N.SUSPENDING]: N.SUSPENDED, [N.UNSUSPENDING]: N.EXECUTE,
             [N.STOPPING]: N.STOPPED, [N.ABORTING]: N.ABORTED, [N.CLEARING]: N.STOPPED };
const ALL = Object.values(N);
const COMMANDS = {
    Reset: [[N.STOPPED, N.COMPLETE], N.RESETTING],
    Start: [[N.IDLE], N.STARTING],
    Stop: [ALL.filter((s) => ![N.STOPPING, N.STOPPED, N.ABORTING, N.ABORTED, N.CLEARING].includes(s)), N.STOPPING],
    Abort: [ALL.filter((s) => ![N.ABORTING, N.ABORTED].includes(s)), N.ABORTING],
    Clear: [[N.ABORTED], N.CLEARING],
    Hold: [[N.EXECUTE, N.SUSPENDED], N.HOLDING],
    Unhold: [[N.HELD], N.UNHOLDING],
    Suspend: [[N.EXECUTE], N.SUSPENDING],
    Unsuspend: [[N.SUSPENDED], N.UNSUSPENDING],
    ToComplete: [[N.EXECUTE, N.HELD, N.SUSPENDED], N.COMPLETING],
};
// where each state sits in the three nested machines of OPC 30050
const BASE = { [N.ABORTING]: "Aborting", [N.ABORTED]: "Aborted" };
const MACHINE = { [N.CLEARING]: "Clearing", [N.STOPPED]: "Stopped", [N.STOPPING]: "Stopping" };

const users = options.users ?? null;
const serverOptions = {
    port: options.port ?? 4850,
    host: "127.0.0.1", // loopback only
    hostname: "127.0.0.1",
    nodeset_filename: [nodesets.standard, nodesets.packML],
    buildInfo: { productName: "test PLC (node-opcua)", manufacturerName: "packml_ros2 tests" },
    allowAnonymous: !users,
    userManager: users ? { isValidUser: (name, password) => users[name] === password } : undefined,
};
if (options.secure) {
    const pki = options.pki;
    fs.mkdirSync(pki, { recursive: true });
    const serverCertificateManager = new OPCUACertificateManager({ rootFolder: `${pki}/server`, automaticallyAcceptUnknownCertificate: true });
    await serverCertificateManager.initialize();
    serverOptions.serverCertificateManager = serverCertificateManager;
    serverOptions.securityPolicies = [SecurityPolicy.Basic256Sha256];
    serverOptions.securityModes = [MessageSecurityMode.Sign, MessageSecurityMode.SignAndEncrypt];
}
const server = new OPCUAServer(serverOptions);
await server.initialize();
const as = server.engine.addressSpace;
const p = as.getNamespaceIndex(PACKML_URI);
const own = as.getOwnNamespace();
const folder = as.rootFolder.objects.getFolderElementByName("PackMLObjects", p);
const methods = [
    ...["Abort", "Clear"].map((m) => `BaseStateMachine.${m}`),
    ...["Stop", "Reset"].map((m) => `BaseStateMachine.MachineState.${m}`),
    ...["Reset", "Start", "Hold", "Unhold", "Suspend", "Unsuspend", "ToComplete"].map((m) => `BaseStateMachine.MachineState.ExecuteState.${m}`),
];
const unit = as.findObjectType("PackMLBaseObjectType", p).instantiate({
    browseName: { name: options.unit ?? "wrapper", namespaceIndex: own.index },
    organizedBy: folder,
    optionals: ["Status.StateRequested", "Status.StateChangeInProcess", "Admin.StopReason", "Admin.Alarm",
                "Admin.ProdProcessedCount", "Admin.ProdDefectiveCount", ...methods],
});
const child = (node, ...names) => names.reduce((n, name) => n.getChildByName(name, name === "CurrentState" || name === "Id" ? 0 : p), node);
const base = child(unit, "BaseStateMachine");
const machine = child(base, "MachineState");
const execute = child(machine, "ExecuteState");
const machines = [
    [base, "PackMLBaseStateMachineType"], [machine, "PackMLMachineStateMachineType"], [execute, "PackMLExecuteStateMachineType"],
].map(([node, type]) => ({ node, type: as.findObjectType(type, p) }));
const status = (name) => child(unit, "Status", name);
const admin = (name) => child(unit, "Admin", name);
const structure = (name) => as.findDataType(name, p);

// -- the machine ------------------------------------------------------------------------------------------
let state = N.STOPPED;
let mode = 1;
let speed = 0;
let fault = null; // the active or latched alarm
let stopReason = null;
let processed = 0;
let timer = null;

function alarmValue(a) {
    return as.constructExtensionObject(structure("PackMLAlarmDataType"), a ? {
        ID: a.id, value: a.value ?? 0, message: a.message ?? "", category: a.category ?? 0,
        dateTime: a.at, ackDateTime: null, trigger: a.active,
    } : {});
}

function places(s) {
    if (BASE[s]) return [BASE[s], null, null];
    if (MACHINE[s]) return ["Cleared", MACHINE[s], null];
    return ["Cleared", "Running", NAME[s][0] + NAME[s].slice(1).toLowerCase()];
}

function write(node, dataType, value, arrayType) {
    node.setValueFromSource(new Variant({ dataType, value, arrayType: arrayType ?? VariantArrayType.Scalar }));
}

function publish() {
    // every value of one step is written in one go (a PLC's cycle)
    places(state).forEach((place, i) => {
        const { node, type } = machines[i];
        const current = node.getChildByName("CurrentState", 0);
        const id = current.getChildByName("Id", 0);
        if (place === null) {
            current.setValueFromSource(new Variant({ dataType: DataType.LocalizedText, value: new LocalizedText({ text: "" }) }), StatusCodes.BadStateNotActive);
            id.setValueFromSource(new Variant({ dataType: DataType.NodeId, value: NodeId.nullNodeId }), StatusCodes.BadStateNotActive);
            return;
        }
        write(current, DataType.LocalizedText, new LocalizedText({ text: place, locale: "en" }));
        write(id, DataType.NodeId, type.getComponentByName(place, p).nodeId);
    });
    const requested = SC[state] && state !== N.EXECUTE ? settle(state) : state;
    write(status("StateRequested"), DataType.Int32, requested);
    write(status("StateChangeInProcess"), DataType.Boolean, Boolean(SC[state]) && state !== N.EXECUTE);
    write(status("UnitModeCurrent"), DataType.Int32, mode);
    write(status("MachSpeed"), DataType.Float, speed);
    write(status("CurMachSpeed"), DataType.Float, state === N.EXECUTE ? speed : 0);
    admin("StopReason").setValueFromSource(new Variant({ dataType: DataType.ExtensionObject, value: alarmValue(stopReason) }));
    admin("Alarm").setValueFromSource(new Variant({ dataType: DataType.ExtensionObject, arrayType: VariantArrayType.Array, value: fault ? [alarmValue(fault)] : [] }));
    counts();
}

function counts() {
    const count = (id, name, n) => as.constructExtensionObject(structure("PackMLCountDataType"), { ID: id, name, count: n, accCount: n });
    admin("ProdProcessedCount").setValueFromSource(new Variant({ dataType: DataType.ExtensionObject, arrayType: VariantArrayType.Array, value: [count(1, "wrapped", processed)] }));
}

function settle(s) {
    while (SC[s] && s !== N.EXECUTE) s = SC[s];
    return s;
}

function go(to, cause) {
    clearTimeout(timer);
    state = to;
    if (state === N.EXECUTE) stopReason = null; // producing again: the next stop has its own reason
    publish();
    out({ state, name: NAME[state], cause });
    if (SC[state] && state !== N.EXECUTE) timer = setTimeout(() => go(SC[state], "SC"), dwell);
}

function command(name) {
    const [from, to] = COMMANDS[name];
    if (!from.includes(state)) return StatusCodes.BadInvalidState;
    if ((name === "Reset" || name === "Clear") && fault && fault.active) return StatusCodes.BadInvalidState;
    if ((name === "Reset" || name === "Clear") && fault) fault = null; // a reset clears latched alarms
    if (state === N.EXECUTE && !stopReason && ["Stop", "Abort", "Hold", "Suspend"].includes(name)) {
        stopReason = { id: 1, message: `${name} command`, category: 0, at: new Date(), active: false };
    }
    go(to, name);
    return StatusCodes.Good;
}

setInterval(() => {
    if (state === N.EXECUTE) {
        processed += 1;
        counts();
    }
}, 1000 / (options.rate ?? 10));

// -- methods -------------------------------------------------------------------------------------------------
for (const path of methods) {
    const name = path.split(".").pop();
    const owner = path.split(".").slice(0, -1).reduce((n, part) => child(n, part), unit);
    child(owner, name).bindMethod((inputArguments, context, callback) => {
        callback(null, { statusCode: command(name) });
    });
}
child(unit, "SetUnitMode").bindMethod((inputArguments, context, callback) => {
    const requested = inputArguments[0].value;
    if (![1, 2, 3].includes(requested)) return callback(null, { statusCode: StatusCodes.BadOutOfRange });
    if (![N.STOPPED, N.IDLE, N.ABORTED].includes(state)) return callback(null, { statusCode: StatusCodes.BadInvalidState });
    mode = requested;
    publish();
    callback(null, { statusCode: StatusCodes.Good });
});
child(unit, "SetMachSpeed").bindMethod((inputArguments, context, callback) => {
    const requested = inputArguments[0].value;
    if (!(requested >= 0 && requested <= 100)) return callback(null, { statusCode: StatusCodes.BadOutOfRange });
    speed = requested;
    publish();
    callback(null, { statusCode: StatusCodes.Good });
});

publish();
await server.start();
out({ ready: true, endpoint: server.getEndpointUrl(), namespace: own.namespaceUri });

// -- the test's hand on the machine --------------------------------------------------------------------------
readline.createInterface({ input: process.stdin }).on("line", (line) => {
    const msg = JSON.parse(line);
    if (msg.fault) {
        fault = { ...msg.fault, at: new Date(), active: true };
        if (!stopReason && state !== N.STOPPED && state !== N.ABORTED) stopReason = { ...fault };
        const reaction = msg.fault.reaction === "abort" ? "Abort" : "Stop";
        if (COMMANDS[reaction][0].includes(state)) go(COMMANDS[reaction][1], `alarm ${fault.id}`);
        else publish();
    }
    if (msg.clear && fault) {
        fault = { ...fault, active: false };
        publish();
    }
    if ("blocked" in msg) write(status("EquipmentBlocked"), DataType.Boolean, msg.blocked);
    if ("starved" in msg) write(status("EquipmentStarved"), DataType.Boolean, msg.starved);
    if (msg.command) command(msg.command);
});
process.stdin.on("end", async () => {
    await server.shutdown(0);
    process.exit(0);
});
