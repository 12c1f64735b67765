"""Surveyed scene from GeoJSON: lane lateral distance on straight and curved lines, objects, errors."""
import json
import math

import numpy as np
import pytest

from v2xpos.geo import lla_to_ned, ned_to_lla
from v2xpos.scene import Scene, SceneError
from v2xpos.types import FixStatus, NavState

ORIGIN = np.array([math.radians(39.75), math.radians(-105.2), 1650.0])


def lonlat(ned_points, heights=True) -> list:
    lla = ned_to_lla(np.atleast_2d(np.asarray(ned_points, float)), ORIGIN)
    return [[math.degrees(p[1]), math.degrees(p[0])] + ([p[2]] if heights else []) for p in lla]


def feature(gtype, coords, **props) -> dict:
    return {"type": "Feature", "geometry": {"type": gtype, "coordinates": coords}, "properties": props}


def write(tmp_path, features, name="site.geojson"):
    path = tmp_path / name
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    return path


def master(ned=(0.0, 0.0, 0.0), yaw=0.0, v=(0.0, 0.0, 0.0), rate=(0.0, 0.0, 0.0)) -> NavState:
    lla = ned_to_lla(np.asarray(ned, float), ORIGIN)
    return NavState(t_s=100.0, lla=lla, v_ned_mps=np.asarray(v, float), acc_body_mps2=np.zeros(3),
                    rate_body_rps=np.asarray(rate, float), rpy_rad=np.array([0.0, 0.0, yaw]), fix=FixStatus.FIXED)


def test_straight_lane_signed_lateral_distance_and_speed(tmp_path):
    line = lonlat([[-100, 1.8, 0], [0, 1.8, 0], [100, 1.8, 0]])
    scene = Scene.load(write(tmp_path, [feature("LineString", line, id="right-edge")]), strict=True)
    res = scene.evaluate(master(v=(10.0, 0.5, 0.0)))
    assert res.lane_ids == ["right-edge"]
    assert res.lane_lateral_m[0] == pytest.approx(1.8, abs=1e-4)
    assert res.lane_lateral_speed_mps[0] == pytest.approx(-0.5, abs=1e-6)   # drifting towards it
    res = scene.evaluate(master(yaw=math.pi, v=(-10.0, 0.5, 0.0)))
    assert res.lane_lateral_m[0] == pytest.approx(-1.8, abs=1e-4)         # now on the left
    assert res.lane_lateral_speed_mps[0] == pytest.approx(0.5, abs=1e-6)
    # measurement point 1 m to the right of the reference point
    res = scene.evaluate(master(), measurement_point_body_m=[2.0, 1.0, 0.0])
    assert res.lane_lateral_m[0] == pytest.approx(0.8, abs=1e-4)


def test_curved_lane_matches_circle_distance(tmp_path):
    center, radius = np.array([0.0, 50.0]), 51.8
    ang = np.radians(np.arange(210.0, 330.0, 0.2))
    arc = np.column_stack([center[0] + radius * np.cos(ang), center[1] + radius * np.sin(ang), np.zeros(len(ang))])
    # radius 51.8 about (0, 50): passes 1.8 m to the left of the origin heading north
    scene = Scene.load(write(tmp_path, [feature("LineString", lonlat(arc, heights=False), id="curve")]))
    for n, e, yaw in [(0.0, 0.0, 0.0), (10.0, 2.0, 0.2), (-20.0, 5.0, -0.4)]:
        res = scene.evaluate(master(ned=(n, e, 0.0), yaw=yaw))
        exact = radius - math.hypot(n - center[0], e - center[1])
        assert exact > 0 and res.lane_lateral_m[0] == pytest.approx(-exact, abs=2e-3)  # line to the left
    # driving north, the line (curving right) closes in from the left: d(lateral)/dt = d|p - c|/dt
    for n, e in [(0.0, 0.0), (10.0, 2.0)]:
        res = scene.evaluate(master(ned=(n, e, 0.0), v=(10.0, 0.0, 0.0)))
        expect = (n - center[0]) * 10.0 / math.hypot(n - center[0], e - center[1])
        assert res.lane_lateral_speed_mps[0] == pytest.approx(expect, abs=0.02)  # 0.2 deg chords


def test_points_and_polygons_distance_bearing_ttc(tmp_path):
    feats = [feature("Point", lonlat([20.0, 0.0, 0.0])[0], id="cone", kind="cone"),
             feature("Point", lonlat([0.0, -5.0, 0.0])[0], id="pole"),
             feature("Polygon", [lonlat([[10, -2, 0], [10, 2, 0], [14, 2, 0], [14, -2, 0], [10, -2, 0]])],
                     id="barrier")]
    scene = Scene.load(write(tmp_path, feats), strict=True)
    res = scene.evaluate(master(v=(10.0, 0.0, 0.0)))
    assert res.object_ids == ["cone", "pole", "barrier"]
    np.testing.assert_array_equal(res.object_kind, [0, 0, 1])
    np.testing.assert_allclose(res.object_distance_m, [20.0, 5.0, 10.0], atol=1e-4)
    np.testing.assert_allclose(res.object_bearing_rad, [0.0, -math.pi / 2, 0.0], atol=1e-5)
    assert res.object_ttc_s[0] == pytest.approx(2.0, abs=1e-4)
    assert math.isnan(res.object_ttc_s[1])
    assert res.object_ttc_s[2] == pytest.approx(1.0, abs=1e-4)
    inside = scene.evaluate(master(ned=(12.0, 0.5, 0.0)))
    assert inside.object_distance_m[2] == 0.0


def test_many_points_vectorised_equal_direct_computation(tmp_path):
    rng = np.random.default_rng(4)
    pts = np.column_stack([rng.uniform(-300, 300, 150), rng.uniform(-300, 300, 150), rng.uniform(-3, 3, 150)])
    scene = Scene.load(write(tmp_path, [feature("Point", c, id=f"p{i}") for i, c in enumerate(lonlat(pts))]))
    m = master(ned=(5.0, -3.0, 0.0), yaw=0.9)
    res = scene.evaluate(m)
    ned = lla_to_ned(ned_to_lla(pts, ORIGIN), m.lla)
    np.testing.assert_allclose(res.object_distance_m, np.hypot(ned[:, 0], ned[:, 1]), atol=1e-6)
    np.testing.assert_allclose(res.object_bearing_rad,
                               np.angle(np.exp(1j * (np.arctan2(ned[:, 1], ned[:, 0]) - 0.9))), atol=1e-9)


def test_errors_name_file_feature_and_field(tmp_path):
    good = feature("LineString", lonlat([[0, 0, 0], [10, 0, 0]]), id="ok")
    bad_coord = feature("LineString", [[-105.2, 39.75], [-105.2, "north"]], id="bad")
    bad_type = feature("Circle", [0, 0])
    path = write(tmp_path, [good, bad_coord, bad_type], name="bad_site.geojson")
    scene = Scene.load(path)
    assert [f.id for f in scene.lanes] == ["ok"]            # the rest of the file is kept
    assert len(scene.errors) == 2
    e1, e2 = scene.errors
    assert "bad_site.geojson" in str(e1) and e1.feature_index == 1 and e1.field == "geometry.coordinates[1]"
    assert e2.feature_index == 2 and e2.field == "geometry.type" and "Circle" in str(e2)
    with pytest.raises(SceneError) as info:
        Scene.load(path, strict=True)
    assert info.value.feature_index == 1
    lat_bad = write(tmp_path, [feature("Point", [10.0, 95.0])], name="lat.geojson")
    with pytest.raises(SceneError, match=r"lat.geojson: feature 0: field 'geometry.coordinates': latitude"):
        Scene.load(lat_bad, strict=True)
    notjson = tmp_path / "broken.geojson"
    notjson.write_text("{ nope")
    with pytest.raises(SceneError, match="broken.geojson: not JSON"):
        Scene.load(notjson)
    notjson.write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(SceneError, match="broken.geojson: not JSON"):
        Scene.load(notjson)
    with pytest.raises(SceneError, match="field 'type'"):
        Scene.load(_write_raw(tmp_path, {"type": "Feature"}))
    with pytest.raises(SceneError, match="cannot read"):
        Scene.load(tmp_path / "missing.geojson")


def _write_raw(tmp_path, doc):
    p = tmp_path / "raw.geojson"
    p.write_text(json.dumps(doc))
    return p


def test_scene_results_go_out_on_can_and_udp(tmp_path):
    import uuid

    import can

    from v2xpos.output.can import CanOutput, decode_frames
    from v2xpos.output.udp import build_datagram, parse_datagram, records_from_scene
    feats = [feature("LineString", lonlat([[-50, 1.8, 0], [50, 1.8, 0]]), id="edge"),
             feature("Point", lonlat([20.0, 0.0, 0.0])[0], id="cone")]
    res = Scene.load(write(tmp_path, feats), strict=True).evaluate(master(v=(10.0, 0.0, 0.0)))
    channel = f"scene-{uuid.uuid4().hex}"
    rx = can.Bus(channel=channel, interface="virtual")
    with CanOutput(channel=channel, interface="virtual") as out:
        assert out.send_scene(res) == 2
    frames = []
    while (f := rx.recv(timeout=0.05)) is not None:
        frames.append(f)
    rx.shutdown()
    dec = decode_frames(frames)
    assert dec["lanes"][0]["LateralDist"] == pytest.approx(1.8, abs=1e-3)
    assert dec["objects"][0]["Distance"] == pytest.approx(20.0, abs=1e-3)
    assert dec["objects"][0]["TTC"] == pytest.approx(2.0, abs=0.01)
    lanes, objects = records_from_scene(res)
    d = parse_datagram(build_datagram([], 1, 0.0, lanes, objects))
    assert d.lanes[0].lateral_m == pytest.approx(1.8, abs=1e-3) and d.objects[0].ttc_s == pytest.approx(2.0, abs=1e-3)
