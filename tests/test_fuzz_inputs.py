"""Fuzzing: decoder, pipeline, readers and loaders never crash and every input gets a verdict;
malformed configs and GeoJSON errors name the file and the field."""
from __future__ import annotations

import json
import math
import random
from pathlib import Path

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bench import fuzz
from v2xpos.wire import WireError, decode_state, encode_state, pack_envelope
from tests.shared_data import SHARED_DATA, require_shared

DATA = SHARED_DATA


@pytest.mark.slow
def test_mutation_fuzz_all_targets_zero_crashes():
    report = fuzz.run_fuzz(total=12_000, seed=11, progress=False)
    assert report["fuzz_crashes"] == 0, {k: v["crash_examples"] for k, v in report["targets"].items()}
    assert report["fuzz_inputs"] >= 11_900
    assert report["fuzz_decoded"] + report["fuzz_rejected"] == report["fuzz_inputs"]
    targets = report["targets"]
    assert set(targets) >= {"wire.state", "wire.relative", "master.pipeline", "rtklib_pos", "timetag",
                            "imu_csv", "ubx", "geojson", "master_config", "trust_list"}
    # the mutator reaches both outcomes and many distinct rejection reasons in the decoder
    assert targets["wire.state"]["decoded"] > 0 and targets["wire.state"]["rejected"] > 5000
    assert len(targets["wire.state"]["top_reasons"]) >= 10
    assert targets["master.pipeline"]["decoded"] > 0
    # loader errors name the file (fuzz_unnamed_errors lists loaders whose messages do not)
    assert report["fuzz_unnamed_errors"] == {}


def test_harness_detects_a_crash():
    """A decoder with a bug (KeyError on a missing field) is caught and its input kept."""
    def buggy(data: bytes) -> None:
        try:
            body = msgpack.unpackb(msgpack.unpackb(data)[1])
        except Exception:
            raise WireError("not msgpack") from None
        if not isinstance(body, dict):
            raise WireError("not a map")
        body["lat"]  # noqa: B018  (the bug: a missing field is not turned into a WireError)

    seeds, _ = fuzz.seed_state_payloads()
    target = fuzz._wire_target("buggy", buggy, seeds)
    stats = fuzz.run_target(target, 3000, random.Random(5))
    assert stats.crashes > 0 and stats.rejected > 0
    assert all("KeyError" in c["error"] for c in stats.crash_examples)
    assert stats.crashes + stats.decoded + stats.rejected == stats.inputs


_scalars = st.one_of(st.none(), st.booleans(), st.integers(-2 ** 63, 2 ** 64 - 1), st.floats(),
                     st.text(max_size=80), st.binary(max_size=40))
_values = st.recursive(_scalars, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                        st.dictionaries(st.text(max_size=5), inner, max_size=5)),
                       max_leaves=12)


@pytest.mark.slow
@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(field=st.sampled_from(["fleet", "id", "seq", "t", "fix", "lat", "lon", "h", "v", "a", "w", "rpy",
                              "sp", "sv", "sa", "g", "kind", "ver", "T", "tw", "iq"]), value=_values)
def test_any_field_value_is_decoded_or_rejected_with_a_reason(field, value):
    seeds, _ = fuzz.seed_state_payloads()
    body = msgpack.unpackb(msgpack.unpackb(seeds[0])[1])
    body[field] = value
    data = pack_envelope(msgpack.packb(body, use_bin_type=True))
    try:
        msg = decode_state(data)
    except WireError as exc:
        assert exc.reason and (exc.field is None or isinstance(exc.field, str))
        return
    # accepted: then every number is finite and within the schema's ranges
    assert math.isfinite(msg.t_gps_s) and abs(msg.lat_rad) <= math.pi / 2
    assert all(math.isfinite(x) for x in [*msg.v_ned_mps, *msg.pos_sd_m, *msg.rpy_rad])


def test_bad_master_config_names_file_and_field(tmp_path):
    from master.config import MasterConfig
    from slave.config import ConfigError
    cases = {
        "timeout.toml": ('[service]\ntimeout_ms = -5\n', "timeout_ms"),
        "mp.toml": ('[service]\nmeasurement_point_m = [1, "x", 0]\n', "measurement_point_m"),
        "port.toml": ('[output.udp]\nport = 70000\n', "port"),
        "typo.toml": ('[service]\nfleeet = "demo"\n', "fleeet"),
        "type.toml": ('[service]\nfleet = 7\n', "fleet"),
        "binary.toml": ("[service]\nfleet = \"\xff\xfe\"\n".encode("latin-1"), None),
    }
    for name, (text, fld) in cases.items():
        p = tmp_path / name
        p.write_bytes(text if isinstance(text, bytes) else text.encode())
        with pytest.raises(ConfigError) as exc:
            MasterConfig.load(p)
        assert name in str(exc.value)
        if fld:
            assert fld in str(exc.value)


def test_bad_geojson_names_file_feature_and_field(tmp_path):
    from v2xpos.scene import Scene, SceneError
    doc = json.loads(fuzz.GEOJSON_SEED)
    doc["features"][1]["geometry"]["coordinates"] = [-105.1, 95.0]
    doc["features"][2]["geometry"]["coordinates"] = [[[-105.1, "a"]]]
    p = tmp_path / "scene.geojson"
    p.write_text(json.dumps(doc))
    scene = Scene.load(p)
    assert len(scene.errors) == 2
    assert all("scene.geojson" in str(e) for e in scene.errors)
    assert "feature 1" in str(scene.errors[0]) and "coordinates" in str(scene.errors[0])
    with pytest.raises(SceneError, match=r"scene.geojson: feature 1"):
        Scene.load(p, strict=True)
    p.write_text('{"type": "Feature"}')
    with pytest.raises(SceneError, match=r"scene.geojson.*'type'"):
        Scene.load(p)


def test_real_data_seeds_are_used_when_present():
    require_shared(DATA / "drive_0708" / "gnss_1934.pos")
    targets = {t.name: t for t in fuzz.build_targets(Path("/tmp"))}
    assert targets["rtklib_pos"].seeds[0].startswith(b"%")
    assert targets["timetag"].seeds[0].startswith(b"TIMETAG")


def test_bad_slave_config_and_dataset_toml_name_file_and_field(tmp_path):
    from slave.config import ConfigError, SlaveConfig
    from v2xpos.datasets.loader import load_dataset
    p = tmp_path / "slave.toml"
    source = '[source]\ntype = "sim"\nmodel = "truth_noise"\n'      # required; valid here
    p.write_text(source + '[service]\nrate_hz = "fast"\n')
    with pytest.raises(ConfigError, match=r"slave.toml.*rate_hz"):
        SlaveConfig.load(p)
    p.write_text(source + '[security]\nkey_file = 3\n')
    with pytest.raises(ConfigError, match=r"slave.toml.*key_file"):
        SlaveConfig.load(p)
    seed = fuzz._dataset_toml_seed(tmp_path, fuzz._synthetic_imu_csv(), fuzz._synthetic_pos()).decode()
    d = tmp_path / "dataset.toml"
    d.write_text(seed.replace('lever_arm_m = [0.0, 0.0, 0.0]', 'lever_arm_m = [0.0, "x"]'))
    with pytest.raises(ValueError, match=r"dataset.toml.*lever_arm_m"):
        load_dataset(d)
    d.write_text(seed.replace('platform = "car"\n', ''))
    with pytest.raises(ValueError, match=r"dataset.toml.*platform"):
        load_dataset(d)
    d.write_bytes(seed.encode().replace(b"fuzz", b"\xff\xfe"))
    with pytest.raises(ValueError, match=r"dataset.toml"):
        load_dataset(d)
