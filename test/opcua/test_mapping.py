"""Issues 8 and 17, without a network: the OPC 30050 v1.01 mapping of the unit's messages (from the
official NodeSet), AvailableStates/AvailableTransitions from the unit's rules, the argument checks,
the status of a lost unit's values, the answer codes, the ``opcua:`` configuration, users and
permissions, and the diagnostics a refused call carries."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest
import yaml
from asyncua import ua
from asyncua.common.utils import Buffer
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.ua.ua_binary import struct_from_binary, struct_to_binary
from builtin_interfaces.msg import Time
from packml_interfaces.msg import Admin, Alarm, Count, Descriptor, Product, Status

from packml_ros2.core import Cmd, ConfigError, State, load_cell, parse_cell
from packml_ros2.opcua import bridge, mapping, nodeset, security
from packml_ros2.opcua.available import unit_graph
from packml_ros2.opcua.config import check_password, hash_password, parse_opcua
from packml_ros2.opcua.mapping import NOT_ACTIVE, Struct, admin_values, status_values

MODEL = nodeset.load()

P = 2  # the PackML namespace index in these tests
BASE = "BaseStateMachine/CurrentState"
MACHINE = "BaseStateMachine/MachineState/CurrentState"
EXECUTE = "BaseStateMachine/MachineState/ExecuteState/CurrentState"


def test_the_model_comes_from_the_official_nodeset() -> None:
    assert MODEL.version == "1.01"
    assert MODEL.publication_date == dt.datetime(2020, 10, 8, 11, 8, tzinfo=dt.UTC)
    assert [m.path for m in MODEL.machines] == [
        "BaseStateMachine",
        "BaseStateMachine/MachineState",
        "BaseStateMachine/MachineState/ExecuteState",
    ]
    # v1.01: Cleared is i=71 with StateNumber 19, Running i=75 with 18 (v1.00 had them swapped)
    assert MODEL.machines[0].state("Cleared") == nodeset.StateDef("Cleared", 71, 19)
    assert MODEL.machines[1].state("Running") == nodeset.StateDef("Running", 75, 18)
    set_unit_mode = MODEL.method("SetUnitMode")
    assert [(a.name, a.data_type, a.value_rank) for a in set_unit_mode.arguments] == [
        ("RequestedMode", (0, 6), -1)
    ]
    start = MODEL.method("BaseStateMachine/MachineState/ExecuteState/Start")
    assert [(a.name, a.data_type, a.value_rank) for a in start.arguments] == [
        ("Parameter", (1, 16), 1)
    ]


@pytest.mark.parametrize(
    ("state", "base", "machine", "execute"),
    [
        (6, ("Cleared", 19, 71), ("Running", 18, 75), ("Execute", 6, 36)),
        (4, ("Cleared", 19, 71), ("Running", 18, 75), ("Idle", 4, 28)),
        (15, ("Cleared", 19, 71), ("Running", 18, 75), ("Resetting", 15, 27)),
        (17, ("Cleared", 19, 71), ("Running", 18, 75), ("Complete", 17, 38)),
        (2, ("Cleared", 19, 71), ("Stopped", 2, 53), None),
        (7, ("Cleared", 19, 71), ("Stopping", 7, 54), None),
        (1, ("Cleared", 19, 71), ("Clearing", 1, 55), None),
        (8, ("Aborting", 8, 61), None, None),
        (9, ("Aborted", 9, 62), None, None),
    ],
)
def test_state_machines_nest_as_opc30050(state, base, machine, execute) -> None:
    values = mapping.state_machine_values(MODEL, state, P)
    for path, want in ((BASE, base), (MACHINE, machine), (EXECUTE, execute)):
        if want is None:  # a sub state machine that is not active
            assert values[path].status == NOT_ACTIVE
            assert values[f"{path}/Number"].status == NOT_ACTIVE
            continue
        name, number, node = want
        assert values[path].value.Text == name and values[path].status == 0
        assert values[f"{path}/Number"].value == number
        assert values[f"{path}/Id"].value == ua.NodeId(node, P)


def test_every_packml_state_has_a_place() -> None:
    # the deepest active machine's Number is the PackML state number
    for n in range(1, 18):
        values = mapping.state_machine_values(MODEL, n, P)
        deepest = next(
            values[f"{p}/Number"] for p in (EXECUTE, MACHINE, BASE) if values[p].status == 0
        )
        assert deepest.value == n


# -- AvailableStates / AvailableTransitions --------------------------------------------------------------
def _unit(**keys) -> object:
    return parse_cell({"cell": "c", "units": {"u": keys}}).units["u"]


def _names(values: dict[str, mapping.Value], path: str) -> set[str]:
    by_id = {s.id: s.name for m in MODEL.machines for s in m.states}
    by_id |= {t.id: t.name for m in MODEL.machines for t in m.transitions}
    return {
        by_id[v.Identifier] if v.NamespaceIndex == P else f"u:{v.Identifier}"
        for v in values[path].value
    }


ES_AVAILABLE = "BaseStateMachine/MachineState/ExecuteState/Available"


def test_the_graph_follows_the_model_the_mode_and_hold_from() -> None:
    production = unit_graph(_unit(), 1)
    assert production.states == frozenset(State) - {State.UNDEFINED}
    assert production.edges[(State.HELD, State.COMPLETING)] == {Cmd.COMPLETE}  # TR88-2022
    assert production.edges[(State.EXECUTE, State.COMPLETING)] == {Cmd.COMPLETE}  # and SC
    assert production.edges[(State.RESETTING, State.IDLE)] == frozenset()  # State Complete
    maintenance = unit_graph(_unit(), 2)
    assert State.SUSPENDED not in maintenance.states
    assert not [e for e in maintenance.edges if State.SUSPENDING in e]
    old = unit_graph(_unit(model="2015"), 1)
    assert (State.HELD, State.COMPLETING) not in old.edges
    assert (State.SUSPENDED, State.HOLDING) not in old.edges
    starting = unit_graph(_unit(hold_from=["Execute", "Starting"]), 1)
    assert (State.STARTING, State.HOLDING) in starting.edges
    assert (State.SUSPENDED, State.HOLDING) not in starting.edges
    # a command into a disabled acting state is an edge to where it ends
    quick = _unit(modes={"fast": {"number": 4, "disabled_states": ["Resetting"],
                                  "mode_change_states": ["Stopped"]}})  # fmt: skip
    fast = unit_graph(quick, 4)
    assert (State.STOPPED, State.IDLE) in fast.edges
    assert State.RESETTING not in fast.states


def test_available_values_name_the_nodeset_objects_and_extra_transitions() -> None:
    unit = _unit()
    extra = {
        ("BaseStateMachine/MachineState/ExecuteState", "Held", "Completing"): ua.NodeId(
            "x.HeldToCompleting", 1
        )
    }
    values = mapping.available_values(MODEL, unit_graph(unit, 1), P, extra)
    assert _names(values, "BaseStateMachine/AvailableStates") == {"Aborting", "Aborted", "Cleared"}
    assert _names(values, "BaseStateMachine/AvailableTransitions") == {
        "AbortedToCleared", "AbortingToAborted", "ClearedToAborting"
    }  # fmt: skip
    assert _names(values, "BaseStateMachine/MachineState/AvailableTransitions") == {
        "ClearingToStopped", "RunningToStopping", "StoppedToRunning", "StoppingToStopped"
    }  # fmt: skip
    transitions = _names(values, f"{ES_AVAILABLE}Transitions")
    assert {"SuspendedToHolding", "ExecuteToSuspending", "u:x.HeldToCompleting"} <= transitions
    assert "StartingToHolding" not in transitions  # not in hold_from
    manual = mapping.available_values(MODEL, unit_graph(unit, 3), P, extra)
    assert _names(manual, f"{ES_AVAILABLE}States") == {
        "Resetting", "Idle", "Starting", "Execute"
    }  # fmt: skip
    assert _names(manual, f"{ES_AVAILABLE}Transitions") == {
        "ResettingToIdle", "IdleToStarting", "StartingToExecute"
    }  # fmt: skip
    # Resetting disabled: Reset from Stopped still leads into Running
    fast = _unit(modes={"fast": {"number": 4, "disabled_states": ["Resetting"],
                                 "mode_change_states": ["Stopped"]}})  # fmt: skip
    values = mapping.available_values(MODEL, unit_graph(fast, 4), P, {})
    assert "StoppedToRunning" in _names(
        values, "BaseStateMachine/MachineState/AvailableTransitions"
    )
    assert "ResettingToIdle" not in _names(values, f"{ES_AVAILABLE}Transitions")


def test_extra_transitions_are_the_rules_the_nodeset_lacks() -> None:
    steps = mapping.transition_steps(MODEL, unit_graph(_unit(), 1))
    modelled = mapping.nodeset_transitions(MODEL)
    es = "BaseStateMachine/MachineState/ExecuteState"
    assert {s: c for s, c in steps.items() if s not in modelled} == {
        (es, "Held", "Completing"): "ToComplete",
        (es, "Suspended", "Completing"): "ToComplete",
    }
    assert steps[("BaseStateMachine/MachineState", "Running", "Stopping")] == "Stop"
    assert steps[("BaseStateMachine", "Cleared", "Aborting")] == "Abort"


def test_a_lost_units_values_are_bad_or_uncertain() -> None:
    assert mapping.lost_status("Status/StateCurrent") == ua.StatusCodes.BadCommunicationError
    assert mapping.lost_status(f"{MACHINE}/Number") == ua.StatusCodes.BadCommunicationError
    uncertain = ua.StatusCodes.UncertainLastUsableValue
    assert mapping.lost_status("Admin/ProdProcessedCount") == uncertain
    assert mapping.lost_status("Status/MachSpeed/EURange") == uncertain  # configuration


def test_arguments_are_checked_against_the_nodeset_signature() -> None:
    start = MODEL.method("BaseStateMachine/MachineState/ExecuteState/Start")
    speed = MODEL.method("SetMachSpeed")
    descriptor = type("PackMLDescriptorDataType", (), {})()  # as generated from the NodeSet
    count = type("PackMLCountDataType", (), {})()
    S = ua.StatusCodes

    def status(method, *args) -> tuple[int, int | None]:
        with pytest.raises(bridge.BadArguments) as err:
            bridge.check_arguments(MODEL, method, args)
        return err.value.status, err.value.index

    assert status(start) == (S.BadArgumentsMissing, None)
    assert status(start, ua.Variant([], ua.VariantType.ExtensionObject), ua.Variant(1)) == (
        S.BadTooManyArguments, None
    )  # fmt: skip
    assert status(start, ua.Variant(1, ua.VariantType.Int32)) == (S.BadTypeMismatch, 0)
    assert status(speed, ua.Variant(1.0, ua.VariantType.Double)) == (S.BadTypeMismatch, 0)
    assert status(speed, ua.Variant([1.0], ua.VariantType.Float)) == (S.BadTypeMismatch, 0)
    assert bridge.check_arguments(MODEL, speed, [ua.Variant(2.5, ua.VariantType.Float)]) == [2.5]
    # an empty or null array is no parameter at all
    assert bridge.check_arguments(
        MODEL, start, [ua.Variant([], ua.VariantType.ExtensionObject)]
    ) == [[]]
    assert bridge.check_arguments(MODEL, start, [ua.Variant()]) == [[]]
    assert bridge.check_arguments(MODEL, start, [ua.Variant([descriptor])]) == [[descriptor]]
    assert status(start, ua.Variant([count])) == (S.BadTypeMismatch, 0)


def test_commands_from_opc_ua_name_opc_ua_and_the_user() -> None:
    assert security.command_source("operator") == "opcua:operator"
    assert security.command_source("") == "opcua:anonymous"


def _status(**kw) -> Status:
    msg = Status(
        unit="filler", unit_mode_current=1, unit_mode_requested=1, state_current=6,
        state_requested=6, mach_speed=40.0, cur_mach_speed=40.0,
        parameter=[Descriptor(id=3, name="fill volume", unit="ml", value=500.0)],
        product=[Product(product_id=7, process_variables=[Descriptor(id=1, name="t", unit="s", value=2.0)])],
    )  # fmt: skip
    msg.equipment_interlock.blocked = True
    for k, v in kw.items():
        setattr(msg, k, v)
    return msg


def test_status_values() -> None:
    v = status_values(_status(), MODEL, P)
    assert v["Status/UnitModeCurrent"].value == 1
    assert v["Status/UnitModeRequested"].value is False
    assert v["Status/StateRequested"].value == 6
    assert v["Status/StateChangeInProcess"].value is False
    assert v["Status/MachSpeed"] == mapping.Value(40.0, ua.VariantType.Float)
    assert (
        v["Status/EquipmentBlocked"].value is True and v["Status/EquipmentStarved"].value is False
    )
    assert v["Status/StateCurrent"].value == 6
    (param,) = v["Status/Parameter"].value
    assert param.type == "PackMLDescriptorDataType"
    assert param.fields["ID"] == 3 and param.fields["Value"] == 500.0
    assert param.fields["Unit"].DisplayName.Text == "ml"
    (product,) = v["Status/Product"].value
    assert product.fields["ProductID"] == 7 and len(product.fields["ProcessVariables"]) == 1
    # a requested mode change: OPC 30050's UnitModeRequested is a Boolean
    changing = status_values(
        _status(unit_mode_requested=2, unit_mode_change_in_process=True), MODEL, P
    )
    assert changing["Status/UnitModeRequested"].value is True
    assert changing["Status/UnitModeChangeInProcess"].value is True  # v1.01 name


def test_v2_draft_status_members() -> None:
    """StackLight: one UInt32 per light (bits 0-1 the mode, bit 2 of the first the horn), the
    colours alongside; EquipmentInterlock {Blocked, Starved}; the recipe in use."""
    msg = _status(recipe_current=2, recipe_requested=3, recipe_change_in_process=True)
    msg.stack_light.colors = ["red", "amber", "green"]
    msg.stack_light.modes = [0, 2, 1]
    msg.stack_light.horn = True
    msg.recipe_result = "refused by gripper"
    v = status_values(msg, MODEL, P)
    assert v["Status/StackLight"] == mapping.Value([0b100, 2, 1], ua.VariantType.UInt32)
    assert v["Status/StackLight/Colors"].value == ["red", "amber", "green"]
    assert v["Status/EquipmentInterlock/Blocked"].value is True
    assert v["Status/EquipmentInterlock/Starved"].value is False
    assert v["Status/RecipeCurrent"] == mapping.Value(2, ua.VariantType.Int32)
    assert v["Status/RecipeRequested"].value == 3
    assert v["Status/RecipeChangeInProcess"] == mapping.Value(True, ua.VariantType.Boolean)
    assert v["Status/RecipeResult"].value == "refused by gripper"
    dark = status_values(_status(), MODEL, P)
    assert dark["Status/StackLight"].value == [] and dark["Status/RecipeCurrent"].value == 0


def test_recipe_members_are_plain_typed_nodes(tmp_path: Path) -> None:
    from test.recipe_cell import write_recipe_cell

    unit = load_cell(write_recipe_cell(tmp_path, "c")).units["filler"]
    members = {
        "/".join(name for name, _ in m.path): (m.value, m.prop)
        for m in mapping.recipe_members(unit.recipes.recipes.values())
    }
    T = ua.VariantType
    assert members["Recipe_1"] == (None, False)  # an object
    assert members["Recipe_1/ID"] == (mapping.Value(1, T.Int32), False)
    assert members["Recipe_1/Name"][0] == mapping.Value("cola 0.5", T.String)
    assert members["Recipe_1/PrimaryQty"][0] == mapping.Value(1200.0, T.Float)
    pv = "Recipe_1/ProcessVariables"
    assert members[f"{pv}/Parameter_REAL/fill_volume"][0] == mapping.Value(500.0, T.Float)
    assert members[f"{pv}/Parameter_REAL/fill_volume/Unit"] == (mapping.Value("ml", T.String), True)
    assert members[f"{pv}/Parameter_REAL/fill_volume/ID"] == (mapping.Value(1, T.Int32), True)
    assert members[f"{pv}/Parameter_STRING/label"][0] == mapping.Value("COLA-500", T.String)
    assert members[f"{pv}/Parameter_DINT/valves"][0] == mapping.Value(12, T.Int32)
    assert members[f"{pv}/Parameter_LREAL"] == (None, False)  # every array, even an empty one
    syrup = "Recipe_1/Ingredients/Ingredient_7/Parameter_LREAL/syrup_ratio"
    assert members[syrup][0] == mapping.Value(12.5, T.Double)
    assert members["Recipe_1/Ingredients/Ingredient_7/IngredientID"][0].value == 7
    assert members["Recipe_2/ProcessVariables/Parameter_STRING/label"][0].value == "AQUA-1000"
    # NodeId parts are IDs: unique even when two parameters share a name (browse names made so)
    from packml_ros2.core.recipes import Param, ParamType, Recipe

    twins = Recipe(
        9, "x", process_variables=(Param(1, "a"), Param(2, "a"), Param(3, type=ParamType.DINT))
    )
    names = ["/".join(n for n, _ in m.path) for m in mapping.recipe_members([twins])]
    real = "Recipe_9/ProcessVariables/Parameter_REAL"
    assert {f"{real}/a_1", f"{real}/a_2"} <= set(names)
    assert "Recipe_9/ProcessVariables/Parameter_DINT/Parameter_3" in names


def _alarm(id_: int, trigger: bool = True, acked: bool = False) -> Alarm:
    a = Alarm(id=id_, value=1, message=f"alarm {id_}", category=2, trigger=trigger)
    a.stamp = Time(sec=1_700_000_000, nanosec=250_000_000)
    if acked:
        a.ack_stamp = Time(sec=1_700_000_060)
    return a


def test_admin_values() -> None:
    msg = Admin(unit="filler", mach_design_speed=50.0, acc_time_since_reset=42)
    msg.alarm = [_alarm(201), _alarm(202, trigger=False, acked=True)]
    msg.alarm_extent = 2
    msg.alarm_history = [_alarm(201)]
    msg.alarm_history_extent = 1
    msg.prod_processed_count = [Count(id=1, name="bottles", unit="pcs", count=5, acc_count=12)]
    msg.mode_current_time = list(range(32))
    msg.state_current_time = list(range(32 * 18))
    msg.state_cumulative_time = [0] * (32 * 18)
    v = admin_values(msg)
    first, second = v["Admin/Alarm"].value
    assert first.fields["ID"] == 201 and first.fields["Trigger"] is True
    assert first.fields["Message"] == "alarm 201" and first.fields["Category"] == 2
    assert first.fields["DateTime"] == dt.datetime(2023, 11, 14, 22, 13, 20, 250000, tzinfo=dt.UTC)
    assert first.fields["AckDateTime"] == mapping.NULL_TIME  # not acknowledged: the null DateTime
    assert second.fields["AckDateTime"].year == 2023 and second.fields["Trigger"] is False
    assert v["Admin/AlarmExtent"].value == 2
    assert v["Admin/StopReason"].value.fields["ID"] == 0  # StopReasonExtent 0: an empty entry
    (count,) = v["Admin/ProdProcessedCount"].value
    assert count == Struct(
        "PackMLCountDataType",
        {
            "ID": 1,
            "Name": "bottles",
            "Unit": mapping.eu_information("pcs"),
            "Count": 5,
            "AccCount": 12,
        },
    )
    assert v["Admin/StateCurrentTime"].dims == (32, 18)
    assert v["Admin/StateCurrentTime"].value[1 * 18 + 6] == 24  # [Production, Execute]
    assert v["Admin/ModeCurrentTime"].value[1] == 1
    assert v["Admin/AccTimeSinceReset"].value == 42
    assert v["Status/MachSpeed/EURange"].value.High == 50.0


def test_engineering_units() -> None:
    eu = mapping.eu_information("pcs")
    assert eu.UnitId == (ord("H") << 16) | (ord("8") << 8) | ord("7")  # UN/CEFACT H87, piece
    assert eu.NamespaceUri == mapping.UNECE_URI
    assert mapping.eu_information("bottles").UnitId == -1


def test_refusals_map_to_bad_status_codes() -> None:
    S = ua.StatusCodes
    assert mapping.result_status(True, 0) == 0
    assert mapping.result_status(False, 2) == S.BadInvalidState  # COMMAND_NOT_ALLOWED
    assert mapping.result_status(False, 5) == S.BadOutOfRange  # MODE_UNKNOWN
    assert mapping.result_status(False, 16) == S.BadUserAccessDenied
    assert mapping.result_status(False, 99) == S.BadInvalidState
    assert mapping.result_status(False, 20) == S.BadNotFound  # RECIPE_UNKNOWN
    assert mapping.result_status(False, 21) == S.BadInvalidState  # RECIPE_NOT_ALLOWED
    assert mapping.RESULT_NAMES[22] == "RECIPE_CHANGE_IN_PROCESS"
    # every reason the units answer has a name and a status code here
    from packml_interfaces.msg import Result

    codes = {v for k, v in vars(Result).items() if k.isupper() and isinstance(v, int) and v > 0}
    assert codes <= set(mapping.RESULTS), codes - set(mapping.RESULTS)
    assert all(ua.StatusCode(code).is_bad() for _, code in mapping.RESULTS.values())


# -- configuration, users, permissions -----------------------------------------------------------------
def _cell(tmp_path: Path, opcua: dict | None) -> Path:
    doc = {"cell": "c", "units": {"filler": {}, "capper": {}}}
    if opcua is not None:
        doc["opcua"] = opcua
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def test_config_defaults(tmp_path: Path) -> None:
    config = parse_opcua(load_cell(_cell(tmp_path, None)))
    assert config.endpoint == "opc.tcp://127.0.0.1:4840/"
    assert config.units == ("filler", "capper")
    assert config.allow_anonymous and not config.allow_anonymous_write and config.access_control
    assert config.security_policies == (
        "NoSecurity",
        "Basic256Sha256_Sign",
        "Basic256Sha256_SignAndEncrypt",
    )
    assert config.app_uri() == "urn:packml_ros2:c"


def test_config_errors_name_the_key(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NO_SUCH_PACKML_VAR", raising=False)
    monkeypatch.setenv("PACKML_SHORT_PW", "xy")
    bad = {
        "prot": 1,
        "port": 70000,
        "units": ["filler", "nope"],
        "users": {"a": "env:PACKML_SHORT_PW", "b": "env:NO_SUCH_PACKML_VAR"},
        "security_policies": ["Basic256"],
        "certificate": "missing.der",
        "private_key": "key.pem",  # a key without its certificate
    }
    (tmp_path / "key.pem").write_text("-")
    with pytest.raises(ConfigError) as err:
        parse_opcua(load_cell(_cell(tmp_path, bad)))
    paths = dict(err.value.problems)
    assert "did you mean 'port'" in paths["opcua.prot"]
    assert "outside" in paths["opcua.port"]
    assert "unknown unit 'nope'" in paths["opcua.units[1]"]
    assert "too short" in paths["opcua.users.a"]
    assert "NO_SUCH_PACKML_VAR is not set" in paths["opcua.users.b"]
    assert "Basic256" in paths["opcua.security_policies[0]"]
    assert "no such file" in paths["opcua.certificate"]
    assert "give both or neither" in paths["opcua"]


def test_max_mach_speed(tmp_path: Path) -> None:
    cell = load_cell(_cell(tmp_path, {"max_mach_speed": 60}))
    assert parse_opcua(cell).max_mach_speed == {"filler": 60.0, "capper": 60.0}
    cell = load_cell(_cell(tmp_path, {"max_mach_speed": {"filler": 80}}))
    config = parse_opcua(cell)
    assert config.max_mach_speed == {"filler": 80.0}
    assert bridge.max_mach_speed(config, cell.units["filler"]) == 80.0
    assert bridge.max_mach_speed(config, cell.units["capper"]) is None  # no design speed either
    designed = parse_cell({"cell": "c", "units": {"u": {"mach_design_speed": 50}}})
    assert bridge.max_mach_speed(parse_opcua(designed), designed.units["u"]) == 50.0
    with pytest.raises(ConfigError) as err:
        parse_opcua(load_cell(_cell(tmp_path, {"max_mach_speed": {"nope": 1, "filler": -2}})))
    problems = dict(err.value.problems)
    assert "unknown unit 'nope'" in problems["opcua.max_mach_speed.nope"]
    assert "opcua.max_mach_speed.filler" in problems


def test_passwords(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    stored = hash_password("s3cret", iterations=1000)
    assert stored.startswith("pbkdf2_sha256$1000$")
    assert check_password("s3cret", stored) and not check_password("S3cret", stored)
    assert check_password("plain", "plain") and not check_password(None, "plain")
    monkeypatch.setenv("PACKML_TEST_PW", "from-env")
    config = parse_opcua(load_cell(_cell(tmp_path, {"users": {"op": "env:PACKML_TEST_PW"}})))
    assert config.users == {"op": "from-env"}


def test_users_and_rules(tmp_path: Path) -> None:
    config = parse_opcua(load_cell(_cell(tmp_path, {"users": {"op": hash_password("pw12", 1000)}})))
    users = security.Users(config, {"scada": b"DER"})
    # a password is judged before asyncua asks (Users.judge, throttled: test_logins.py)
    for verdict, name, expected in (
        (("op", True), "op", User(role=UserRole.User, name="op")),
        (("op", False), "op", None),  # no fall-back to anonymous
        (("op", True), "nobody", None),
        (None, "op", None),  # not judged: refused
    ):
        judged = security._LOGIN.set(verdict)  # type: ignore[arg-type]
        try:
            assert users.get_user(None, name, "pw12") == expected, (verdict, name)
        finally:
            security._LOGIN.reset(judged)
    assert users.get_user(None, certificate=b"DER") == User(role=UserRole.User, name="scada")
    assert users.get_user(None).role is UserRole.Anonymous
    assert users.identity_tokens() == [ua.AnonymousIdentityToken, ua.UserNameIdentityToken]

    rules = security.Rules()
    anonymous, user = User(role=UserRole.Anonymous), User(role=UserRole.User, name="op")
    read = ua.NodeId(ua.ObjectIds.ReadRequest_Encoding_DefaultBinary)
    write = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)
    call = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
    add_nodes = ua.NodeId(ua.ObjectIds.AddNodesRequest_Encoding_DefaultBinary)
    assert rules.check_validity(anonymous, read, None) and rules.check_validity(
        anonymous, call, None
    )
    # a Write passes the service level for both: it is answered per node (BadNotWritable;
    # test_opcua_state_face.py), not with a ServiceFault
    assert rules.check_validity(anonymous, write, None) and rules.check_validity(user, write, None)
    assert not rules.check_validity(user, add_nodes, None)

    # methods: per call, from the session's user
    token = security.CURRENT_USER.set(anonymous)
    try:
        assert security.may_call(config) == (False, "")
    finally:
        security.CURRENT_USER.reset(token)
    token = security.CURRENT_USER.set(user)
    try:
        assert security.may_call(config) == (True, "op")
    finally:
        security.CURRENT_USER.reset(token)


def test_nobody_could_connect_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="nobody could connect"):
        parse_opcua(load_cell(_cell(tmp_path, {"allow_anonymous": False})))


def test_refusal_diagnostics_follow_part6_encoding() -> None:
    """The reason of a refused call travels as DiagnosticInfo: LocalizedText (bit 0x04 on the
    wire, OPC UA Part 6) indexes the response's string table, AdditionalInfo carries it too."""
    token = security._REFUSALS.set({})
    try:
        refused = security.refuse(
            ua.StatusCodes.BadInvalidState, "COMMAND_NOT_ALLOWED", "START not allowed"
        )
        response = ua.CallResponse(Results=[ua.CallMethodResult(), refused])
        security._diagnostics(response, security._REFUSALS.get(), 0x20 | 0x40 | 0x80)
    finally:
        security._REFUSALS.reset(token)
    ok, info = response.DiagnosticInfos
    assert struct_to_binary(ok) == b"\x00"
    raw = struct_to_binary(info)
    assert raw[0] == 0x01 | 0x04 | 0x10  # SymbolicId, LocalizedText, AdditionalInfo
    table = response.ResponseHeader.StringTable
    assert table[int.from_bytes(raw[1:5], "little")] == "COMMAND_NOT_ALLOWED"
    assert table[int.from_bytes(raw[5:9], "little")] == "START not allowed"
    assert struct_from_binary(ua.DiagnosticInfo, Buffer(raw)).AdditionalInfo == "START not allowed"


def test_security_warnings_and_trusted_client_certificates(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import asyncio

    monkeypatch.setenv("PACKML_TEST_PW", "abcd")

    from asyncua.crypto import cert_gen
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding
    from cryptography.x509.oid import ExtendedKeyUsageOID

    from packml_ros2.opcua.server import warnings

    open_ = parse_opcua(
        load_cell(_cell(tmp_path, {"host": "0.0.0.0", "allow_anonymous_write": True,
                                   "users": {"a": "env:PACKML_TEST_PW"},
                                   "security_policies": ["None"]}))
    )  # fmt: skip
    assert len(warnings(open_)) == 3
    assert warnings(parse_opcua(load_cell(_cell(tmp_path, None)))) == []

    def certificate(name: str) -> tuple[Path, x509.Certificate]:
        key = cert_gen.generate_private_key()
        cert = cert_gen.generate_self_signed_app_certificate(
            key, name, {}, [x509.UniformResourceIdentifier(f"urn:{name}")],
            [ExtendedKeyUsageOID.CLIENT_AUTH], days=1,
        )  # fmt: skip
        path = tmp_path / f"{name}.der"
        path.write_bytes(cert.public_bytes(Encoding.DER))
        return path, cert

    trusted_path, trusted = certificate("mes")
    _, stranger = certificate("stranger")

    async def check() -> None:
        validate = await security.trusted_validator((trusted_path,))
        await validate(trusted, None)
        with pytest.raises(ua.UaStatusCodeError):
            await validate(stranger, None)

    asyncio.run(check())


def test_user_names_are_recorded_as_they_are_or_refused_at_their_key(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every OPC UA action reaches a unit as opcua:<user>: a user name outside the source
    grammar (or the anonymous sessions' name) is a configuration error, not a user whose every
    action is recorded under another name."""
    monkeypatch.setenv("PACKML_TEST_PW", "long enough password")
    (tmp_path / "c.der").write_bytes(b"-")
    pw = "env:PACKML_TEST_PW"
    bad = {"users": {"mes operator": pw, "josé": pw, "x" * 65: pw, "anonymous": pw, "mes@line-3.x": pw},
           "user_certificates": {"a/b": "c.der", "scada_1": "c.der"}}  # fmt: skip
    with pytest.raises(ConfigError) as err:
        parse_opcua(load_cell(_cell(tmp_path, bad)))
    paths = dict(err.value.problems)
    for key in ("users.mes operator", "users.josé", f"users.{'x' * 65}", "users.anonymous",
                "user_certificates.a/b"):  # fmt: skip
        assert "is not a user name" in paths.pop(f"opcua.{key}"), key
    assert "anonymous sessions" in str(err.value)
    assert paths == {}  # mes@line-3.x and scada_1 are names


def test_iteration_counts_are_bounded_at_load_and_unknown_names_never_logged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 25 item 9 (in part): a stored hash of 10**9 iterations made every guess, and the
    rightful user's login, cost minutes of a core in the event loop; every refused user name was
    logged whole (1 MB of it)."""
    import logging

    huge = hash_password("pw12", 1000).replace("$1000$", "$1000000000$")
    for users, key in (({"op": huge}, "opcua.users.op"),):
        with pytest.raises(ConfigError) as err:
            parse_opcua(load_cell(_cell(tmp_path, {"users": users})))
        assert "1000000000 iterations" in dict(err.value.problems)[key]
    assert not check_password("pw12", huge)  # (what a store from elsewhere could hold)
    doc = {"cell": "c", "units": {"u": {}}, "hmi": {"users": {"anna": {"level": "operator", "password": huge}}}}  # fmt: skip
    from packml_ros2.hmi import hmi_settings

    with pytest.raises(ConfigError) as err:
        hmi_settings(parse_cell(doc))
    assert "1000000000 iterations" in str(err.value)
    config = parse_opcua(load_cell(_cell(tmp_path, {"users": {"op": hash_password("pw12", 1000)}})))
    users = security.Users(config, {})
    caplog.set_level(logging.WARNING)
    # a password is judged before asyncua asks (Users.judge: test_logins.py); unjudged: refused
    assert users.get_user(None, "x" * 1_000_000, "guess") is None
    assert users.get_user(None, "op", "pw12") is None
    assert caplog.records == []


def test_cell_object_is_checked(tmp_path: Path) -> None:
    cell = load_cell(_cell(tmp_path, {"cell_object": True}))
    assert parse_opcua(cell).cell_object
    assert not parse_opcua(load_cell(_cell(tmp_path, {}))).cell_object
    off = parse_cell({"cell": "c", "units": {"u": {}}, "coordinator": {"enabled": False},
                      "opcua": {"cell_object": True}})  # fmt: skip
    with pytest.raises(ConfigError) as err:
        parse_opcua(off)
    assert "enable the coordinator" in dict(err.value.problems)["opcua.cell_object"]
    same = parse_cell({"cell": "u", "units": {"u": {}}, "opcua": {"cell_object": True}})
    with pytest.raises(ConfigError) as err:
        parse_opcua(same)
    assert "named 'u' like the cell" in dict(err.value.problems)["opcua.cell_object"]
