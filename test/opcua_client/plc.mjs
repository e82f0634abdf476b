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
//           "rate": 10 (pieces per second in Execute),
//           "model": "2022" | "2015" (2015: Hold only from EXECUTE; ToComplete only from EXECUTE),
//           "modes": {"1": [], "2": ["SUSPENDING", "SUSPENDED", "UNSUSPENDING"]} (the unit modes there
//               are, each with the states it disables; default {"1": [], "2": [], "3": []}; modes
//               1..31; EXECUTE cannot be disabled),
//           "times": false (true: Admin.StateCurrentTime, StateCumulativeTime [32,18] (index mode*18
//               + state), ModeCurrentTime, ModeCumulativeTime [32], AccTimeSinceReset, whole seconds,
//               refreshed every 250 ms and on every transition),
//           "faults": [names] (deliberate violations of the standard, below)}
// modes: a command whose first target is an acting state disabled in the current mode passes
// through it to its State-Complete successor (while that is a disabled acting state; a skipped state
// is never shown); a command that would settle in a disabled wait state is refused
// (BadInvalidState); SetUnitMode: BadOutOfRange for a mode not in "modes", BadInvalidState unless in
// STOPPED, IDLE or ABORTED and the current state is enabled in the target mode.
// faults: "missing_transition" (Unsuspend in SUSPENDED refused), "skip_acting" (Reset goes straight
// to IDLE), "wrong_target" (Hold in EXECUTE leads to SUSPENDING), "invalid_accepted" (Start accepted
// in STOPPED), "refused_moves" (Start in STOPPED refused, 100 ms later RESETTING anyway), "stuck"
// (COMPLETING never completes), "disabled_entered" (Hold in EXECUTE goes HOLDING -> HELD even where
// the mode disables them), "mode_matrix" (SetUnitMode accepted in EXECUTE too), "mode_not_shown"
// (SetUnitMode Good but Status.UnitModeCurrent keeps the old mode), "times_frozen"
// (StateCurrentTime all 0), "cumulative_lost" (StateCumulativeTime = the current or last stay only),
// "mode_time_frozen" (ModeCurrentTime all 0); the last three imply "times": true. An unknown
// option value or fault name: a message on stderr and exit code 2.
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
const die = (message) => {
    process.stderr.write(`plc.mjs: ${message}\n`);
    process.exit(2);
};

// TR88 state numbers and the TR88-2022 table
const N = { CLEARING: 1, STOPPED: 2, STARTING: 3, IDLE: 4, SUSPENDED: 5, EXECUTE: 6, STOPPING: 7, ABORTING: 8,
            ABORTED: 9, HOLDING: 10, HELD: 11, UNHOLDING: 12, SUSPENDING: 13, UNSUSPENDING: 14, RESETTING: 15,
            COMPLETING: 16, COMPLETE: 17 };
const NAME = Object.fromEntries(Object.entries(N).map(([k, v]) => [v, k]));
const SC = { [N.RESETTING]: N.IDLE, [N.STARTING]: N.EXECUTE, [N.COMPLETING]: N.COMPLETE, [N.HOLDING]: N.HELD,
             [N.UNHOLDING]: N.EXECUTE, [N.SUSPENDING]: N.SUSPENDED, [N.UNSUSPENDING]: N.EXECUTE,
             [N.STOPPING]: N.STOPPED, [N.ABORTING]: N.ABORTED, [N.CLEARING]: N.STOPPED };
const ALL = Object.values(N);
const model = options.model ?? "2022";
if (!["2022", "2015"].includes(model)) die(`unknown model ${JSON.stringify(model)}`);
const COMMANDS = {
    Reset: [[N.STOPPED, N.COMPLETE], N.RESETTING],
    Start: [[N.IDLE], N.STARTING],
    Stop: [ALL.filter((s) => ![N.STOPPING, N.STOPPED, N.ABORTING, N.ABORTED, N.CLEARING].includes(s)), N.STOPPING],
    Abort: [ALL.filter((s) => ![N.ABORTING, N.ABORTED].includes(s)), N.ABORTING],
    Clear: [[N.ABORTED], N.CLEARING],
    Hold: [model === "2015" ? [N.EXECUTE] : [N.EXECUTE, N.SUSPENDED], N.HOLDING],
    Unhold: [[N.HELD], N.UNHOLDING],
    Suspend: [[N.EXECUTE], N.SUSPENDING],
    Unsuspend: [[N.SUSPENDED], N.UNSUSPENDING],
    ToComplete: [model === "2015" ? [N.EXECUTE] : [N.EXECUTE, N.HELD, N.SUSPENDED], N.COMPLETING],
};
// the unit modes: mode number -> the states it disables
const MODES = new Map(Object.entries(options.modes ?? { 1: [], 2: [], 3: [] }).map(([key, names]) => {
    const m = Number(key);
    if (!Number.isInteger(m) || m < 1 || m > 31) die(`mode ${JSON.stringify(key)} is not 1..31`);
    if (!Array.isArray(names)) die(`mode ${m}: expected a list of state names`);
    for (const name of names) {
        if (!N[name]) die(`mode ${m}: unknown state ${JSON.stringify(name)}`);
        if (name === "EXECUTE") die(`mode ${m}: EXECUTE cannot be disabled`);
    }
    return [m, new Set(names.map((name) => N[name]))];
}));
if (!MODES.size) die("no mode in \"modes\"");
const FAULT_NAMES = ["missing_transition", "skip_acting", "wrong_target", "invalid_accepted", "refused_moves", "stuck",
                     "disabled_entered", "mode_matrix", "mode_not_shown", "times_frozen", "cumulative_lost", "mode_time_frozen"];
const faults = new Set(options.faults ?? []);
for (const name of faults) if (!FAULT_NAMES.includes(name)) die(`unknown fault ${JSON.stringify(name)}`);
const times = options.times === true || ["times_frozen", "cumulative_lost", "mode_time_frozen"].some((f) => faults.has(f));
const MODE_DIM = 32;
const STATE_DIM = 18; // TR88 state numbers 0..17
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
                "Admin.ProdProcessedCount", "Admin.ProdDefectiveCount", ...methods,
                ...(times ? ["Admin.StateCurrentTime", "Admin.StateCumulativeTime", "Admin.ModeCurrentTime",
                             "Admin.ModeCumulativeTime", "Admin.AccTimeSinceReset"] : [])],
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
if (times) {
    // the type says [0,0] / [0] (any length); this instance's arrays have fixed lengths
    for (const name of ["StateCurrentTime", "StateCumulativeTime"]) admin(name).arrayDimensions = [MODE_DIM, STATE_DIM];
    for (const name of ["ModeCurrentTime", "ModeCumulativeTime"]) admin(name).arrayDimensions = [MODE_DIM];
}

// -- the machine ------------------------------------------------------------------------------------------
let state = N.STOPPED;
let mode = MODES.has(1) ? 1 : Math.min(...MODES.keys());
let shownMode = mode; // Status.UnitModeCurrent (differs from mode only with the fault "mode_not_shown")
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
    write(status("UnitModeCurrent"), DataType.Int32, shownMode);
    write(status("MachSpeed"), DataType.Float, speed);
    write(status("CurMachSpeed"), DataType.Float, state === N.EXECUTE ? speed : 0);
    admin("StopReason").setValueFromSource(new Variant({ dataType: DataType.ExtensionObject, value: alarmValue(stopReason) }));
    admin("Alarm").setValueFromSource(new Variant({ dataType: DataType.ExtensionObject, arrayType: VariantArrayType.Array, value: fault ? [alarmValue(fault)] : [] }));
    counts();
    if (times) publishTimes();
}

function counts() {
    const count = (id, name, n) => as.constructExtensionObject(structure("PackMLCountDataType"), { ID: id, name, count: n, accCount: n });
    admin("ProdProcessedCount").setValueFromSource(new Variant({ dataType: DataType.ExtensionObject, arrayType: VariantArrayType.Array, value: [count(1, "wrapped", processed)] }));
}

function settle(s) {
    while (SC[s] && s !== N.EXECUTE) s = SC[s];
    return s;
}

const disabled = (s, m = mode) => MODES.get(m).has(s);

// the state a move to `to` shows first: disabled acting states are passed through to their State
// Complete successor; null when the move would settle in a disabled wait state
function route(to) {
    let s = to;
    while (SC[s] && disabled(s)) s = SC[s];
    return disabled(settle(s)) ? null : s;
}

// force: the disabled states of the mode are ignored on the way (the fault "disabled_entered")
function go(to, cause, force = false) {
    clearTimeout(timer);
    if (times) leave(now());
    state = to;
    if (state === N.EXECUTE) stopReason = null; // producing again: the next stop has its own reason
    publish();
    out({ state, name: NAME[state], cause });
    if (SC[state] && state !== N.EXECUTE && !(faults.has("stuck") && state === N.COMPLETING)) {
        timer = setTimeout(() => {
            let next = SC[state];
            while (!force && SC[next] && disabled(next)) next = SC[next];
            go(next, "SC", force);
        }, dwell);
    }
}

function command(name) {
    let [from, to] = COMMANDS[name];
    let force = false;
    if (faults.has("missing_transition") && name === "Unsuspend" && state === N.SUSPENDED) return StatusCodes.BadInvalidState;
    if (faults.has("refused_moves") && name === "Start" && state === N.STOPPED) {
        setTimeout(() => {
            const first = route(N.RESETTING);
            if (state === N.STOPPED && first !== null) go(first, "Start");
        }, 100);
        return StatusCodes.BadInvalidState;
    }
    if (faults.has("invalid_accepted") && name === "Start" && state === N.STOPPED) from = [N.STOPPED];
    if (!from.includes(state)) return StatusCodes.BadInvalidState;
    if ((name === "Reset" || name === "Clear") && fault && fault.active) return StatusCodes.BadInvalidState;
    if (name === "Hold" && state === N.EXECUTE) {
        if (faults.has("wrong_target")) to = N.SUSPENDING;
        if (faults.has("disabled_entered")) force = true;
    }
    let first = force ? to : route(to);
    if (first === null) return StatusCodes.BadInvalidState;
    if (faults.has("skip_acting") && name === "Reset") first = N.IDLE;
    if ((name === "Reset" || name === "Clear") && fault) fault = null; // a reset clears latched alarms
    if (state === N.EXECUTE && !stopReason && ["Stop", "Abort", "Hold", "Suspend"].includes(name)) {
        stopReason = { id: 1, message: `${name} command`, category: 0, at: new Date(), active: false };
    }
    go(first, name, force);
    return StatusCodes.Good;
}

// -- Admin times: milliseconds (high resolution, monotonic) kept, whole seconds shown --------------------
const now = () => performance.now();
const startedAt = now();
let stateSince = startedAt; // the current (mode, state) entered
let modeSince = startedAt;
const stateMs = new Float64Array(MODE_DIM * STATE_DIM); // the ended stays, summed
const lastStayMs = new Float64Array(MODE_DIM * STATE_DIM); // the last ended stay (the fault "cumulative_lost")
const modeMs = new Float64Array(MODE_DIM);
const shown = {};

function leave(t) { // the current (mode, state) stay ends at t
    const i = mode * STATE_DIM + state;
    stateMs[i] += t - stateSince;
    lastStayMs[i] = t - stateSince;
    stateSince = t;
}

function changeMode(to) {
    if (to === mode) return;
    const t = now();
    if (times) {
        leave(t);
        modeMs[mode] += t - modeSince;
        modeSince = t;
    }
    mode = to;
}

function publishTimes() {
    const t = now();
    const sec = (ms) => Math.floor(ms / 1000);
    const here = mode * STATE_DIM + state;
    const stateCurrent = new Int32Array(MODE_DIM * STATE_DIM);
    const stateCumulative = new Int32Array(MODE_DIM * STATE_DIM);
    const modeCurrent = new Int32Array(MODE_DIM);
    const modeCumulative = new Int32Array(MODE_DIM);
    if (!faults.has("times_frozen")) stateCurrent[here] = sec(t - stateSince);
    for (let i = 0; i < stateCumulative.length; i++) {
        if (faults.has("cumulative_lost")) stateCumulative[i] = sec(i === here ? t - stateSince : lastStayMs[i]);
        else stateCumulative[i] = sec(stateMs[i] + (i === here ? t - stateSince : 0));
    }
    if (!faults.has("mode_time_frozen")) modeCurrent[mode] = sec(t - modeSince);
    for (let m = 0; m < MODE_DIM; m++) modeCumulative[m] = sec(modeMs[m] + (m === mode ? t - modeSince : 0));
    const values = { StateCurrentTime: stateCurrent, StateCumulativeTime: stateCumulative,
                     ModeCurrentTime: modeCurrent, ModeCumulativeTime: modeCumulative };
    for (const [name, value] of Object.entries(values)) {
        if (shown[name] && shown[name].every((x, i) => x === value[i])) continue;
        shown[name] = value;
        const matrix = name.startsWith("State");
        admin(name).setValueFromSource(new Variant({
            dataType: DataType.Int32, value,
            arrayType: matrix ? VariantArrayType.Matrix : VariantArrayType.Array,
            dimensions: matrix ? [MODE_DIM, STATE_DIM] : undefined,
        }));
    }
    const acc = sec(t - startedAt);
    if (shown.AccTimeSinceReset !== acc) write(admin("AccTimeSinceReset"), DataType.Int32, (shown.AccTimeSinceReset = acc));
    // besides every 250 ms: again just after the next whole second of any of the running times
    const running = [t - stateSince, stateMs[here] + t - stateSince, t - modeSince, modeMs[mode] + t - modeSince, t - startedAt];
    clearTimeout(timesTimer);
    timesTimer = setTimeout(publishTimes, Math.min(...running.map((ms) => 1000 - (ms % 1000))) + 1);
}
let timesTimer = null;
if (times) setInterval(publishTimes, 250);

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
    if (!MODES.has(requested)) return callback(null, { statusCode: StatusCodes.BadOutOfRange });
    const from = [N.STOPPED, N.IDLE, N.ABORTED, ...(faults.has("mode_matrix") ? [N.EXECUTE] : [])];
    if (!from.includes(state) || disabled(state, requested)) return callback(null, { statusCode: StatusCodes.BadInvalidState });
    changeMode(requested);
    if (!faults.has("mode_not_shown")) shownMode = mode;
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
        const [from, to] = COMMANDS[msg.fault.reaction === "abort" ? "Abort" : "Stop"];
        const first = from.includes(state) ? route(to) : null;
        if (first !== null) go(first, `alarm ${fault.id}`);
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
