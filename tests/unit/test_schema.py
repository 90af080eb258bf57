"""Strict validation of magkf's input documents (``magkf.schema``): calibration files, effect settings, study
specs; effects restored from a calibration name its file; mapped tables, offline tables and ULogs refuse what
they used to read silently or report in another library's words."""

import json
import struct

import numpy as np
import pandas as pd
import pytest

from magkf.calibration import Calibration, StoredEffect
from magkf.effects import LinearEffect, check_columns, restore_effects
from magkf.effects.base import EpochData
from magkf.effects.linear import per_axis
from magkf.errors import InputError
from magkf.io.autopilot import export_instance
from magkf.io.columnmap import read_mapped
from magkf.io.ulog import read_ulog, write_ulog
from magkf.offline.reading import read_offline_table
from magkf.schema import BOOLEAN, INTEGER, NUMBER, STRING, check, numbers, strict
from magkf.study import StudySpec
from magkf.study import run as run_study

from .test_ulog import _synthetic


def _calibration(**extra) -> dict:
    """A version-2 calibration with a temperature effect, as ``calibrate --effect temperature_bias`` writes it."""
    effect = StoredEffect(
        "temperature_bias:temp_c",
        {"column": "temp_c", "T0": 20.0},
        ("k_x", "k_y", "k_z"),
        (3.0, -2.0, 1.0),
        (0.5, 0.5, 0.5),
        ("nT/degC",) * 3,
    )
    cal = Calibration(np.eye(3), [100.0, -50.0, 20.0], method="ekf-both", effects=(effect,), source="flight.csv")
    return cal.to_dict() | extra


def _refusal(data, source="cal.json") -> str:
    with pytest.raises(InputError) as err:
        Calibration.from_dict(data, source)
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"{source}: ")
    return text


def test_an_unknown_key_is_refused_with_the_nearest_known_one():
    assert "unknown key 'covarience' (did you mean 'covariance'?)" in _refusal(_calibration(covarience=[]))
    assert "unknown key 'zzz' (known: format, version" in _refusal(_calibration(zzz=1))
    data = _calibration()
    data["effects"][0]["setings"] = {}
    assert "unknown key 'effects[0].setings' (did you mean 'settings'?)" in _refusal(data)


@pytest.mark.parametrize(
    "value, words",
    [
        ("abc", "key 'effects[0].settings.T0' must be a number, not 'abc'"),
        (None, "key 'effects[0].settings.T0' must be a number, not null"),
        (True, "key 'effects[0].settings.T0' must be a number, not true"),
        (float("nan"), "key 'effects[0].settings.T0' must be a finite number"),
        (1e308, "key 'effects[0].settings.T0' must be at most 1000, not 1e+308"),
        (-300.0, "key 'effects[0].settings.T0' must be at least -273.15, not -300.0"),
    ],
)
def test_effect_settings_are_checked_by_the_effects_schema(value, words):
    data = _calibration()
    data["effects"][0]["settings"]["T0"] = value
    assert words in _refusal(data)


def test_a_builtin_effect_stores_its_own_settings_parameters_and_column():
    data = _calibration()
    data["effects"][0]["settings"]["T_0"] = 3.0
    assert "unknown key 'effects[0].settings.T_0' (did you mean 'T0'?)" in _refusal(data)
    data = _calibration()
    data["effects"][0]["parameters"]["k_w"] = {"value": 1.0}
    assert "has parameters k_x, k_y, k_z, not k_x, k_y, k_z, k_w" in _refusal(data)
    data = _calibration()
    data["effects"][0]["effect"] = "temperature_bias:temp_x"
    assert "the label and the setting must name the same column" in _refusal(data)
    data = _calibration()
    data["effects"][0]["settings"] = {"column": "temp_c", "walk": 1.0}
    assert "unknown key 'effects[0].settings.walk'" in _refusal(data)
    drift = StoredEffect("bias_drift", {"walk": -1.0}, ("d_x", "d_y", "d_z"), (0.0,) * 3, (1.0,) * 3, ("nT",) * 3)
    data = _calibration(effects=[drift.to_dict()])
    assert "key 'effects[0].settings.walk' must be at least 0, not -1.0" in _refusal(data)


def test_the_records_magkf_reads_are_strict_where_it_writes_them():
    errors = {"R11": 0.01, "b_xx": 0.1}
    assert "unknown key 'standard_errors.b_xx' (did you mean 'b_x'?)" in _refusal(_calibration(standard_errors=errors))
    assert "must be a number or null, not 'x'" in _refusal(_calibration(standard_errors={"b_x": "x"}))
    quality = {"status_counts": {"used": 10, "gated_magnitud": 1}}
    assert "unknown key 'quality.status_counts.gated_magnitud'" in _refusal(_calibration(quality=quality))
    model = {"family": "full", "hled": "nothing"}
    assert "unknown key 'model.hled' (did you mean 'held'?)" in _refusal(_calibration(model=model))
    assert "key 'model.held_core' must hold numbers, shape (12,)" in _refusal(_calibration(model={"held_core": [1]}))
    kept = _calibration(standard_errors={"b_x": None}, quality={"coverage": 0.9}, parameters={"anything": [1, "a"]})
    assert Calibration.from_dict(kept, "cal.json").quality == {"coverage": 0.9}  # null: none computed


@pytest.mark.parametrize("index, words", [(1.7, "a whole number or null, not 1.7"), (-1, "at least 0, not -1")])
def test_the_magnetometer_entry_export_reads_is_checked(index, words):
    mag = {"format": "px4-ulog", "instance": 0, "device_id": 7, "calibration_index": index}
    assert f"key 'magnetometer.calibration_index' must be {words}" in _refusal(_calibration(magnetometer=mag))
    good = Calibration.from_dict(_calibration(magnetometer=mag | {"calibration_index": 2}), "cal.json")
    assert export_instance(good, "px4")[0] == 2


def test_every_key_magkf_writes_reads_back():
    """A calibration with every optional key (site, magnetometer, model, a wandering effect's path) round trips."""
    wander = {
        "walk": {"value": 1.5, "std": None, "interval_95": [0.0, 3.0], "unit": "nT/sqrt(s)", "learned": True},
        "departure": {"mean": [0.0, 0.0, 0.0], "rms": [1.0, 2.0, 3.0], "unit": "nT"},
        "span": [10.0, 20.0],
        "fingerprint": {"first": 10.0, "last": 20.0, "n_epochs": 11, "time": [10.0], "mag": [[1.0, 2.0, 3.0]]},
        "path": {"time": [10.0, 20.0], "values": [[0.0] * 3, [1.0] * 3], "std": [[1.0] * 3, [1.0] * 3]},
    }
    drift = StoredEffect("bias_drift", {"walk": 1.5}, ("d_x", "d_y", "d_z"), (0.0,) * 3, (1.0,) * 3, ("nT",) * 3)
    cal = Calibration(
        np.eye(3),
        [1.0, 2.0, 3.0],
        covariance=np.eye(12),
        quality={"residual_rms_nt": 30.0},
        magnetometer={"format": "ardupilot-dataflash", "instance": 0, "compass": 1, "own_key": "kept"},
        site={"given": True, "lat": 48.1, "lon": 11.6, "alt": 0.0, "start_utc": "2026-01-01T00:00:00Z"},
        field_unit="nT",
        model={"family": "full", "text": "everything estimated"},
        effects=(StoredEffect(**vars(drift) | {"wander": wander}),),
    )
    text = json.dumps(cal.to_dict())
    again = Calibration.from_dict(json.loads(text), "cal.json")
    assert again.to_dict() == cal.to_dict() and again.magnetometer["own_key"] == "kept"


def test_restored_effects_name_the_calibration_file_not_its_source_log(tmp_path):
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(_calibration()))
    cal = Calibration.load(path)
    assert cal.file == str(path) and cal.source == "flight.csv"
    (effect,) = restore_effects(cal)
    assert effect.stored_in == str(path)
    with pytest.raises(InputError) as err:
        check_columns([effect], ["speed_mps"], "log.csv")
    assert err.value.source == str(path)
    assert "effect 'temperature_bias:temp_c' needs column 'temp_c', which log.csv lacks" in str(err.value)
    data = EpochData(np.arange(3.0), np.ones((3, 3)), np.ones((3, 3)), {"speed_mps": np.ones(3)})
    with pytest.raises(InputError, match="needs column 'temp_c'") as err:
        effect.jacobian(np.zeros(3), data)  # no KeyError, whichever way the effect is reached
    assert err.value.source == str(path)


class Spiky(LinearEffect):
    """A user's effect (defined outside magkf) that gives inf where its speed passes 20 m/s."""

    name = "spiky_test_effect"
    parameter_names = ("s_x", "s_y", "s_z")

    def __init__(self, column: str = "speed_mps", limit: float = 20.0):
        self.columns = (column,)
        self.limit = limit

    def design(self, data):
        v = np.asarray(data.columns[self.columns[0]], float)
        if np.any(v < 0):
            raise ZeroDivisionError("negative speed")
        return per_axis(np.where(v > self.limit, np.inf, v))


def test_a_user_effect_that_fails_on_the_log_names_its_file():
    field = np.tile([20000.0, 0.0, 43000.0], (4, 1))
    data = EpochData(np.arange(4.0), field, field, {"speed_mps": np.array([1.0, 2.0, 30.0, 3.0])}, mag=field)
    with pytest.raises(
        InputError, match=r"jacobian\(\) gives values that are not finite or beyond 1e9 at 1 of 4"
    ) as err:
        Spiky().contribution(np.ones(3), data)
    assert err.value.source == __file__
    data = EpochData(np.arange(2.0), field[:2], field[:2], {"speed_mps": np.array([-1.0, 1.0])}, mag=field[:2])
    with pytest.raises(InputError, match="fails on the log in jacobian.*ZeroDivisionError: negative speed") as err:
        Spiky().jacobian(np.ones(3), data)
    assert err.value.source == __file__
    with pytest.raises(InputError, match="beyond 1e9 at 1 of 1") as err:
        Spiky(limit=1e300).contribution(
            np.ones(3), EpochData(np.arange(1.0), field[:1], field[:1], {"speed_mps": np.array([1e300])}, mag=field[:1])
        )
    data = EpochData(np.arange(2.0), field[:2], field[:2], {"speed_mps": np.array([np.nan, 1.0])}, mag=field[:2])
    assert np.isnan(Spiky().contribution(np.ones(3), data)[0]).all()  # NaN where its input is missing: fine


def test_a_user_effects_settings_schema_is_read_from_its_constructor():
    schema = Spiky.settings_json_schema()
    assert schema["properties"] == {"column": STRING, "limit": NUMBER} and not schema["additionalProperties"]
    with pytest.raises(InputError, match="key 'effects.settings.limit' must be a number, not 'x'"):
        check({"limit": "x"}, schema, "cal.json", "effects.settings")


def test_schema_messages_name_the_key_path_and_what_would_do():
    schema = strict({"n": INTEGER | {"minimum": 1}, "on": BOOLEAN, "v": numbers((2,))}, ["n"])
    cases = [
        ({"n": 0}, "key 'n' must be at least 1, not 0"),
        ({"n": 1.5}, "key 'n' must be a whole number, not 1.5"),
        ({}, "required key 'n' is missing"),
        ({"n": 1, "onn": True}, "unknown key 'onn' (did you mean 'on'?)"),
        ({"n": 1, "zz": True}, "unknown key 'zz' (known: n, on, v)"),
        ({"n": 1, "v": [1, "a"]}, "key 'v' must hold numbers, shape (2,); v[1] holds 'a'"),
    ]
    for document, words in cases:
        with pytest.raises(InputError) as err:
            check(document, schema, "x.json")
        assert str(err.value) == f"x.json: {words}"


@pytest.mark.parametrize(
    "table, key, words",
    [
        ("study", {"replicate": 3}, "unknown key 'study.replicate' (did you mean 'replicates'?)"),
        ("study", {"seed": -1}, "key 'study.seed' must be at least 0, not -1"),
        ("base", {"b_wlak": 1.0}, "unknown key 'base.b_wlak' (did you mean 'b_walk'?)"),
        ("base", {"b_walk": "fast"}, "key 'base.b_walk' must be a number, not 'fast'"),
        (
            "sample",
            {"count": 2, "b_walk": {"unifrm": [1, 2]}},
            "unknown key 'sample.b_walk.unifrm' (did you mean 'uniform'?)",
        ),
        ("logs", {"path": ["a.csv"]}, "unknown key 'logs.path' (did you mean 'paths'?)"),
    ],
)
def test_a_study_spec_is_strict(table, key, words):
    spec = {table: key} | ({"recipes": [{"duration_s": 60}]} if table != "recipes" else {})
    with pytest.raises(InputError) as err:
        StudySpec.from_dict(spec, "study.toml")
    assert str(err.value) == f"study.toml: {words}"
    with pytest.raises(InputError, match=r"recipes\[0\].duraton_s' \(did you mean 'duration_s'"):
        StudySpec.from_dict({"recipes": [{"duraton_s": 60}]}, "study.toml")


def test_a_study_names_only_logs_and_never_quotes_a_file(tmp_path):
    secret = "SECRET-LINE password=hunter2"
    for name in ("notes.txt", "notes.csv"):
        (tmp_path / name).write_text(f"{secret}\nmore\n")
        with pytest.raises(InputError) as err:
            StudySpec.from_dict({"logs": {"paths": [name]}}, "study.toml", tmp_path)
        assert "SECRET" not in str(err.value) and name in str(err.value) and "not a" in str(err.value)


def test_a_study_whose_every_run_failed_has_its_tables_and_says_so(tmp_path):
    (tmp_path / "bad.csv").write_text("time,mag_x,mag_y,mag_z\n1,2,3,4\n")
    result = run_study(StudySpec.from_dict({"logs": {"paths": ["bad.csv"]}}, "study.toml", tmp_path))
    assert {"nees", "final_b_error_nt"} <= set(result.runs) and result.runs["nees"].isna().all()
    assert result.summary["n_failed"].tolist() == [1]
    assert result.failure.startswith("every run of the study failed (1 run); run 0: ")
    assert "bad.csv" in result.failure


def test_a_short_record_of_a_mapped_table_is_refused_not_padded(tmp_path):
    (tmp_path / "m.toml").write_text('[columns]\ntime = "t"\nmag_x = "x"\nmag_y = "y"\nmag_z = "z"\n')
    rows = ["t,x,y,z", "1.0,20000,100,40000", "2.0,20001,101", "3.0,20002,102,40002"]
    (tmp_path / "s.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(InputError, match="3 fields where the header has 4") as err:
        read_mapped(tmp_path / "s.csv", tmp_path / "m.toml")
    assert err.value.row == 3
    rows[2] = "2.0,20001,101,"  # an empty cell: a missing value, read as one
    (tmp_path / "s.csv").write_text("\n".join(rows) + "\n")
    table, _ = read_mapped(tmp_path / "s.csv", tmp_path / "m.toml")
    assert np.isnan(table["mag_z"].iloc[1]) and len(table) == 3


def test_an_axis_the_fit_would_leave_out_is_refused_with_the_fix(tmp_path):
    pd.DataFrame(np.ones((5, 3)), columns=["mag_x", "mag_y", "mag_z"]).to_csv(tmp_path / "e.csv", index=False)
    with pytest.raises(InputError, match="holds mag_z, which the fit would leave out: give --axes 3"):
        read_offline_table(tmp_path / "e.csv", ["mag_x", "mag_y"], left_out=["mag_z"], fix="give --axes 3")
    table, _ = read_offline_table(tmp_path / "e.csv", ["mag_x", "mag_y"])
    assert list(table.columns[:2]) == ["mag_x", "mag_y"]


def test_a_ulog_whose_attitude_clock_runs_back_is_one_line_naming_it(tmp_path):
    path = tmp_path / "back.ulg"
    write_ulog(_synthetic(300, 3), path)
    data = bytearray(path.read_bytes())
    pos, ids, stamps = 16, set(), []  # the ULog's messages: size (uint16), type (char), payload
    while pos + 3 <= len(data):
        size, kind = struct.unpack_from("<HB", data, pos)
        body = data[pos + 3 : pos + 3 + size]
        if kind == ord("A") and body[3:].decode() == "vehicle_attitude":
            ids.add(struct.unpack_from("<H", body, 1)[0])
        if kind == ord("D") and struct.unpack_from("<H", body, 0)[0] in ids:
            stamps.append(pos + 5)  # timestamp, then timestamp_sample (uint64 each)
        pos += 3 + size
    for field in (0, 8):
        struct.pack_into("<Q", data, stamps[150] + field, struct.unpack_from("<Q", data, stamps[10] + field)[0])
    path.write_bytes(data)
    with pytest.raises(InputError) as err:
        read_ulog(path)
    text = str(err.value)
    assert text.startswith(f"{path}: the vehicle_attitude timestamps go backwards (once; first at sample 150")
    assert "strictly increasing" not in text
