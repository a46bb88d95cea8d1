"""Scene content (groundsim.world.render.scene, scene_config, textures): config, determinism, clouds,
terrain, distractors and their labels, and today's output unchanged when it is all off."""

from __future__ import annotations

import hashlib
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.ndimage import minimum_filter

from groundsim.world.render import IrRenderer, IrSettings, SceneBackground
from groundsim.world.render.clutter import point_detections
from groundsim.world.render.planck import band_radiance
from groundsim.world.render.raster import BOX_FRACTION, PyrUpImage
from groundsim.world.render.scene import FAR_M, ObjectLabel, SceneContent, _occluded_by_nearer, section_rng
from groundsim.world.render.scene_config import CloudsConfig, SceneConfig, scene_config_from_dict
from groundsim.world.render.settings import TargetPart
from groundsim.world.render.textures import cloud_texture
from groundsim.world.scenario import load_scenario, scenarios_dir
from onboard.core.errors import InputError
from onboard.core.frames import PinholeIntrinsics, quat_from_euler, rotmat_from_quat
from onboard.core.schema import SchemaError

INTR = PinholeIntrinsics.vue_pro_640()
CENTROID_TOL_PX = 0.5  # label centroid vs the intensity-weighted centroid of the drawn object
DEPTH_RTOL = 0.01  # plane ranges through the 4 px grid and two pyrUp steps
# sha256 of the P1 frames below, rendered by the renderer before the scene hook existed
P1_SHA256 = {
    "mono8": "6b4c22f1d34e99ec10978b4bef0330400a8ee3d18a68592e91cf32f111bd02df",
    "mono16": "49177d0110daba80af995207cfef64c962b4983248049961dc53e674a2f941b8",
}


def look_at(p_cam, p_t, roll_rad=0.0) -> np.ndarray:
    """R_ned_from_cam of a camera at p_cam looking at p_t (image x right, y down), rolled about its axis."""
    z = (p_t - p_cam) / np.linalg.norm(p_t - p_cam)
    x = np.cross(np.array([0.0, 0.0, 1.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    return np.stack([x, y, z], axis=1) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def looking(pitch_deg: float, yaw_deg: float = 20.0) -> np.ndarray:
    """A camera looking along azimuth yaw_deg, pitch_deg above the horizon (-90: straight down)."""
    el, az = math.radians(pitch_deg), math.radians(yaw_deg)
    d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), -math.sin(el)])
    up = np.array([0.0, 0.0, -1.0]) if abs(pitch_deg) < 89.0 else np.array([-math.cos(az), -math.sin(az), 0.0])
    x = np.cross(d, up)
    x /= np.linalg.norm(x)
    y = np.cross(d, x)
    return np.stack([x, y, d], axis=1)


def scene(cfg: dict, seed: int = 3, **ir) -> tuple[SceneContent, IrRenderer]:
    r = IrRenderer(INTR, IrSettings(encoding="mono16", **ir), seed=1)
    return SceneContent.from_config(scene_config_from_dict(cfg), r, seed), r


# ---------------------------------------------------------------------------- today's output unchanged


def test_p1_frames_byte_identical_to_the_renderer_before_the_scene_hook():
    sc = load_scenario(scenarios_dir() / "P1.yaml")
    for enc, want in P1_SHA256.items():
        r = IrRenderer(sc.camera.intrinsics, replace(sc.ir, encoding=enc), seed=5)
        h = hashlib.sha256()
        for k in range(0, 300, 15):
            t = k / 30.0
            p_o = sc.observer.motion.state(t).p_ned_m
            p_t = sc.target.motion.state(t).p_ned_m
            aim = p_t + np.array([0.0, 0.0, 40.0 * math.sin(0.5 * t)])  # the horizon sweeps through the image
            R_t = rotmat_from_quat(quat_from_euler(0.1, -0.05, 0.3 * t))
            h.update(r.render(p_o, look_at(p_o, aim, 0.1 * math.sin(t)), p_t, R_t, 0.0).tobytes())
        assert h.hexdigest() == want, enc


def test_scene_off_is_todays_background_and_quantise_matches_render():
    sc, r = scene({})
    p, R = np.array([0.0, 0.0, -80.0]), looking(-3.0)
    bg = sc.render_background(p, R, 0.0)
    assert np.array_equal(bg.radiance, r.base_radiance(p, R, 0.0))
    assert np.all(bg.depth_m == FAR_M) and not bg.cloud_alpha.any()
    r1 = IrRenderer(INTR, IrSettings(encoding="mono16"), seed=9)
    r2 = IrRenderer(INTR, IrSettings(encoding="mono16"), seed=9)
    today = r1.render(p, R, None, None, 0.0).astype(int)
    hooked = r2.quantise(r2.base_radiance(p, R, 0.0)).astype(int)
    assert np.max(np.abs(today - hooked)) <= 1  # float rounding of grey -> radiance -> grey
    assert np.mean(today != hooked) < 5e-3  # float32 holds ~3e4 grey to 0.002: a few roundings flip


# ---------------------------------------------------------------------------- config


def test_config_all_off_by_default_and_errors_name_the_field():
    cfg = SceneConfig()
    assert not cfg.has_content and not cfg.sensor.enabled
    assert scene_config_from_dict(None) == cfg
    with pytest.raises(SchemaError, match=r"C1.yaml: clouds.cover_fraction: expected .*1.*got 1.5"):
        scene_config_from_dict({"clouds": {"cover_fraction": 1.5}}, "C1.yaml")
    with pytest.raises(SchemaError, match=r"terrain.roof_temp_k: .*did you mean 'roof_temperature_k'"):
        scene_config_from_dict({"terrain": {"roof_temp_k": 300.0}}, "C2.yaml")
    with pytest.raises(SchemaError, match=r"distractors.birds.count: expected"):
        scene_config_from_dict({"distractors": {"birds": {"count": 2.0}}})
    with pytest.raises(SchemaError, match=r"distractors.aircraft\[0\].p0_ned_m"):
        scene_config_from_dict({"distractors": {"aircraft": [{"p0_ned_m": [1.0, 2.0]}]}})
    with pytest.raises(SchemaError, match=r"sensor.counts_at_t_max: expected at most 16383"):
        scene_config_from_dict({"sensor": {"counts_at_t_max": 20000}})
    with pytest.raises(SchemaError, match=r"sensor.ffc.mode"):
        scene_config_from_dict({"sensor": {"ffc": {"mode": "freeze"}}})
    # settings written without ``enabled`` drew nothing, silently: refused naming the key to add
    with pytest.raises(SchemaError, match=r"^C1.yaml: clouds.enabled: expected true .*the section sets cover_fraction"):
        scene_config_from_dict({"clouds": {"cover_fraction": 0.4}}, "C1.yaml")
    with pytest.raises(SchemaError, match=r"^C5.yaml: sensor.fpn.enabled: expected true .*sets hot_pixels"):
        scene_config_from_dict({"sensor": {"enabled": True, "fpn": {"hot_pixels": 3}}}, "C5.yaml")
    assert not scene_config_from_dict({"clouds": {"enabled": False, "cover_fraction": 0.4}}).clouds.enabled
    assert scene_config_from_dict({"clouds": {"enabled": True, "cover_fraction": 0.4}}).clouds.cover_fraction == 0.4
    assert scene_config_from_dict({"clouds": {}}) == cfg


def test_bad_constructor_inputs():
    r = IrRenderer(INTR, IrSettings(), seed=1)
    with pytest.raises(InputError, match="config"):
        SceneContent({"clouds": {}}, r, 0)
    with pytest.raises(InputError, match="seed"):
        SceneContent(SceneConfig(), r, -1)


# ---------------------------------------------------------------------------- determinism

FULL = {
    "clouds": {"enabled": True, "texture_px": 256, "texel_m": 40.0},
    "terrain": {"enabled": True, "texture_px": 512, "texel_m": 1.0, "building_count": 40},
    "distractors": {
        "birds": {"count": 3, "center_ned_m": [120.0, 40.0, -90.0], "spread_m": 30.0},
        "aircraft": [{"p0_ned_m": [3000.0, 800.0, -700.0]}],
        "glints": [{"p_ned_m": [250.0, 90.0, 0.0]}],
    },
}


def _frame_bytes(seed: int) -> bytes:
    sc, _ = scene(FULL, seed=seed)
    p, R = np.array([0.0, 0.0, -100.0]), looking(2.0)
    out = b""
    for k in range(3):
        f = sc.render(k / 30.0, p, R, p + R @ np.array([0.05, 0.0, 1.0]) * 150.0, np.eye(3), 0.0)
        out += f.radiance.tobytes() + f.background.depth_m.tobytes() + repr(f.labels).encode()
    return out


def test_same_seed_same_bytes_other_seed_other_bytes():
    a, b, c = _frame_bytes(4), _frame_bytes(4), _frame_bytes(5)
    assert a == b
    assert a != c


def test_section_rng_depends_on_its_own_section_only():
    x = section_rng(1, "clouds", 0).random(4)
    assert np.array_equal(x, section_rng(1, "clouds", 0).random(4))
    assert not np.array_equal(x, section_rng(1, "terrain", 0).random(4))
    assert not np.array_equal(x, section_rng(1, "clouds", 1).random(4))


# ---------------------------------------------------------------------------- clouds

CLOUDS = {"clouds": {"enabled": True, "texture_px": 512, "texel_m": 20.0, "base_altitude_m": 1200.0}}


def test_cloud_cover_fraction_and_sunlit_edges():
    band = (7.5, 13.5)
    cfg = CloudsConfig(enabled=True, texture_px=256, texel_m=20.0, cover_fraction=0.3)
    tex = cloud_texture(cfg, band, np.random.default_rng(0))
    assert np.mean(tex.density > 0.0) == pytest.approx(0.3, abs=0.01)
    L0 = float(band_radiance(cfg.brightness_temperature_k, band))
    L3 = float(band_radiance(cfg.brightness_temperature_k + 3.0, band))
    cold = cloud_texture(replace(cfg, sun_edge_warming_k=0.0), band, np.random.default_rng(0))
    assert np.percentile(cold.radiance, 99.5) < L3  # no warming: only the 0.1 K fine variation
    assert np.percentile(tex.radiance, 99.5) > L3  # edges lit by the sun: up to 6 K warmer
    # the warm edges face the sun (azimuth 135 deg: south-east): texels just sun-ward of cloud are clear
    warm = tex.radiance > L3
    az = math.radians(cfg.sun_azimuth_deg)
    di, dj = round(3 * math.cos(az)), round(3 * math.sin(az))
    sunward = np.roll(np.roll(tex.density, -di, axis=0), -dj, axis=1)
    shadeward = np.roll(np.roll(tex.density, di, axis=0), dj, axis=1)
    assert sunward[warm].mean() < shadeward[warm].mean()
    assert np.mean(tex.radiance > L0 - 1e-3 * L0) > 0.5


def test_cloud_depth_is_the_layer_and_clouds_are_warmer_than_the_sky():
    sc, _ = scene(CLOUDS)
    p = np.array([0.0, 0.0, -100.0])
    bg = sc.render_background(p, looking(90.0), 0.0)  # straight up
    assert bg.depth_m[256, 320] == pytest.approx(1100.0, rel=DEPTH_RTOL)
    corner_ray = INTR.bearing_cam_from_pixel(np.array([40.5, 40.5]))
    assert bg.depth_m[40, 40] == pytest.approx(1100.0 / corner_ray[2], rel=DEPTH_RTOL)
    cloudy = bg.cloud_alpha > 0.9
    clear = bg.cloud_alpha == 0.0
    assert cloudy.mean() > 0.05 and clear.mean() > 0.05
    assert np.all(bg.radiance[cloudy] > bg.base_radiance[cloudy])  # 268 K cloud over a ~230 K zenith sky
    assert np.array_equal(bg.radiance[clear], bg.base_radiance[clear])
    down = sc.render_background(p, looking(-60.0), 0.0)
    assert not down.cloud_alpha.any()  # the layer is above a camera looking down


def test_depth_and_opacity_windows_are_the_whole_images_values():
    """The objects and labels read the depth and the cloud opacity by window from the coarse grid: the same
    values as the whole image there, inside and at every border (where pyrUp reflects), for odd sizes too."""
    rng = np.random.default_rng(5)
    for shape in ((512, 640), (30, 45)):
        coarse = rng.uniform(0.0, 1.0, (-(-shape[0] // 4), -(-shape[1] // 4))).astype(np.float32)
        coarse[rng.uniform(size=coarse.shape) < 0.3] = FAR_M  # the depth's far value beside cloud ranges
        whole = PyrUpImage(coarse, shape).full()
        assert whole.shape == shape
        shared = PyrUpImage(coarse, shape)  # keeps its windows: later ones inside them are read from them
        for _ in range(300):
            i0, j0 = int(rng.integers(0, shape[0])), int(rng.integers(0, shape[1]))
            i1, j1 = int(rng.integers(i0 + 1, shape[0] + 1)), int(rng.integers(j0 + 1, shape[1] + 1))
            win = PyrUpImage(coarse, shape).window(slice(i0, i1), slice(j0, j1))
            assert np.array_equal(win, whole[i0:i1, j0:j1]), (shape, i0, i1, j0, j1)
            # a small window and single pixels in and next to it, as an object's region and its label read them
            i1, j1 = min(i0 + int(rng.integers(1, 12)), shape[0]), min(j0 + int(rng.integers(1, 12)), shape[1])
            for a, b, c, d in ((i0, i1, j0, j1), (i0, i0 + 1, j0, j0 + 1), (i1 - 1, i1, j1 - 1, j1)):
                for di, dj in ((0, 0), (3, -2), (-5, 6)):
                    a2, c2 = min(max(a + di, 0), shape[0] - 1), min(max(c + dj, 0), shape[1] - 1)
                    rows, cols = (
                        slice(a2, max(min(b + di, shape[0]), a2 + 1)),
                        slice(c2, max(min(d + dj, shape[1]), c2 + 1)),
                    )
                    assert np.array_equal(shared.window(rows, cols), whole[rows, cols]), (shape, rows, cols)
    sc, _ = scene(CLOUDS)
    bg = sc.render_background(np.array([0.0, 0.0, -100.0]), looking(30.0), 0.0)
    rows, cols = slice(100, 140), slice(0, 37)
    depth_w, alpha_w = bg.depth_window(rows, cols), bg.alpha_window(rows, cols)
    assert np.array_equal(depth_w, bg.depth_m[rows, cols]) and np.array_equal(alpha_w, bg.cloud_alpha[rows, cols])
    assert bg.cloud_alpha.any() and bg.depth_m.min() < 2000.0  # the window held clouds to compare


def test_target_behind_a_cloud_is_occluded_in_front_visible():
    sc, _ = scene(CLOUDS)
    p = np.array([0.0, 0.0, -100.0])
    R = looking(90.0)
    bg = sc.render_background(p, R, 0.0)
    ii, jj = np.nonzero(bg.cloud_alpha[60:-60, 60:-60] > 0.999)
    i, j = ii[len(ii) // 2] + 60, jj[len(jj) // 2] + 60
    ray = R @ INTR.bearing_cam_from_pixel(np.array([j + 0.5, i + 0.5]))
    depth = float(bg.depth_m[i, j])
    big = (("body", "ellipsoid", (0.0, 0.0, 0.0), (3.0, 3.0, 3.0), 320.0, 0.9),)
    parts = tuple(TargetPart(*b) for b in big)
    r = IrRenderer(INTR, IrSettings(encoding="mono16", target_parts=parts), seed=1)
    sc = SceneContent.from_config(scene_config_from_dict(CLOUDS), r, 3)
    behind = sc.render(0.0, p, R, p + ray * (depth + 300.0), np.eye(3), 0.0).labels[0]
    front = sc.render(0.0, p, R, p + ray * (depth - 300.0), np.eye(3), 0.0).labels[0]
    assert behind.visibility == "occluded" and front.visibility == "visible"
    assert behind.contrast_netd < 0.01 * front.contrast_netd
    assert front.contrast_netd > 10.0


@pytest.mark.parametrize("temperature_k, warm", [(320.0, True), (260.0, False)])
def test_warm_is_the_sign_of_the_contrast_the_label_measures(temperature_k, warm):
    # looking down at the 290 K ground: a 320 K body is a warm point, a 260 K one a cold point of about
    # the same |contrast| (both far above 3 NETD), which contrast_netd alone does not tell apart
    parts = (TargetPart("body", "ellipsoid", (0.0, 0.0, 0.0), (0.5, 0.5, 0.5), temperature_k, 0.9),)
    r = IrRenderer(INTR, IrSettings(encoding="mono16", target_parts=parts), seed=1)
    sc = SceneContent.from_config(scene_config_from_dict(None), r, 3)
    p, R = np.array([0.0, 0.0, -100.0]), looking(-60.0)
    fr = sc.render(0.0, p, R, p + R[:, 2] * 60.0, np.eye(3), 0.0)
    lab = fr.labels[0]
    assert lab.visibility == "visible" and lab.contrast_netd > 100.0
    assert lab.warm is warm
    x0, y0, x1, y1 = lab.box_px
    diff = fr.radiance[y0:y1, x0:x1] - fr.background.radiance[y0:y1, x0:x1]
    assert bool(diff.max() > -diff.min()) is warm  # the image agrees with the label
    # the box (ends exclusive) is the extent of the pixels whose |signal| reaches BOX_FRACTION of the peak
    # (0.1 % either side of the threshold for float32 rounding of the signal added to the background)
    signal = np.abs(fr.radiance - fr.background.radiance)
    for fraction, inside in ((1.001 * BOX_FRACTION, True), (0.999 * BOX_FRACTION, False)):
        ii, jj = np.nonzero(signal >= fraction * signal.max())
        extent = (jj.min(), ii.min(), jj.max() + 1, ii.max() + 1)
        if inside:
            assert x0 <= extent[0] and y0 <= extent[1] and extent[2] <= x1 and extent[3] <= y1, (lab.box_px, extent)
        else:
            assert extent[0] <= x0 and extent[1] <= y0 and x1 <= extent[2] and y1 <= extent[3], (lab.box_px, extent)


def test_a_label_is_occluded_only_by_a_nearer_box_holding_its_centre_pixel():
    """``_occluded_by_nearer``: the centre's pixel (floor of u, v) inside a nearer object's box (ends exclusive)."""

    def lab(object_id, u, v, range_m, box=None):
        return ObjectLabel(object_id, "target", u, v, box, "visible", 5.0 if box else 0.0, range_m)

    far = lab(1, 10.9, 20.9, 500.0)  # pixel (row 20, column 10)
    for box, occluded in (((5, 15, 11, 21), True), ((5, 15, 10, 21), False), ((5, 15, 11, 20), False)):
        near = lab(0, 8.0, 18.0, 100.0, box)
        out = _occluded_by_nearer((near, far))
        assert [x.visibility for x in out] == ["visible", "occluded" if occluded else "visible"], box
        # a box of a farther object hides nothing
        out = _occluded_by_nearer((replace(near, range_m=900.0), far))
        assert [x.visibility for x in out] == ["visible", "visible"]


# ---------------------------------------------------------------------------- terrain

TERRAIN = {"terrain": {"enabled": True, "texture_px": 1024, "texel_m": 0.5}}


def _texel_of(sc: SceneContent, material: int) -> tuple[float, float]:
    """(north, east) of the centre of a 9 x 9 texel patch of one material."""
    m = sc.terrain.material == material
    core = minimum_filter(m.astype(np.uint8), size=9, mode="wrap").astype(bool)
    ii, jj = np.nonzero(core)
    k = len(ii) // 2
    return (ii[k] + 0.5) * sc.terrain.texel_m, (jj[k] + 0.5) * sc.terrain.texel_m


@pytest.mark.parametrize("material,key", [(1, "road"), (2, "roof"), (3, "water"), (0, "field")])
def test_terrain_material_radiance_at_nadir(material, key):
    sc, r = scene(TERRAIN, extinction_per_km=0.0)
    n, e = _texel_of(sc, material)
    h = 200.0
    p = np.array([n, e, -h])
    bg = sc.render_background(p, looking(-90.0), 0.0)
    assert bg.depth_m[256, 320] == pytest.approx(h, rel=DEPTH_RTOL)
    cfg, s = sc.config.terrain, r.settings
    T = sc.terrain.temperature_k[int(n / cfg.texel_m), int(e / cfg.texel_m)]
    eps = getattr(cfg, f"{key}_emissivity")
    L_sky = float(band_radiance(0.5 * (s.sky_zenith_k + s.sky_horizon_k), s.band_um))
    L_sky_down = float(band_radiance(s.sky_zenith_k, s.band_um))  # the flat ground reflects the zenith at nadir
    L_flat = s.ground_emissivity * float(band_radiance(s.ground_temperature_k, s.band_um))
    want = L_flat + (1 - s.ground_emissivity) * L_sky_down
    want += eps * float(band_radiance(T, s.band_um)) + (1 - eps) * L_sky - (L_flat + (1 - s.ground_emissivity) * L_sky)
    assert bg.radiance[256, 320] == pytest.approx(want, rel=2e-3)
    if key in ("road", "roof"):
        assert T > s.ground_temperature_k + 10.0  # hot by day
    if key == "water":
        assert T < cfg.field_temperature_k - 5.0


def test_terrain_perspective_road_width_in_pixels():
    """A road of width w seen straight down from height h is w f / h pixels wide."""
    sc, _ = scene(TERRAIN, extinction_per_km=0.0)
    n, e = _texel_of(sc, 1)
    road = sc.terrain.material == 1
    i, j = int(n / 0.5), int(e / 0.5)
    north_south = road[(i + 30) % road.shape[0], j] and road[(i - 30) % road.shape[0], j]
    h = 150.0
    bg = sc.render_background(np.array([n, e, -h]), looking(-90.0, yaw_deg=0.0), 0.0)
    # yaw 0 looking down: image up = north, image x = east: a north-south road is a vertical band
    profile = bg.radiance[250:262].mean(axis=0) if north_south else bg.radiance[:, 314:326].mean(axis=1)
    hot = profile > 0.5 * (profile.max() + np.median(profile))
    c = 320 if north_south else 256
    lo, hi = c, c
    while hot[lo - 1]:
        lo -= 1
    while hot[hi + 1]:
        hi += 1
    assert hot[c]
    assert hi - lo + 1 == pytest.approx(sc.config.terrain.road_width_m * INTR.fx_px / h, abs=3.0)


# ---------------------------------------------------------------------------- distractors and labels


def _signal(sc, r, t, p, R):
    f = sc.render(t, p, R, None, None, 0.0)
    return f, f.radiance - f.background.radiance


def test_labels_agree_with_the_rendered_pixels():
    cfg = {
        "distractors": {
            "birds": {"count": 4, "center_ned_m": [90.0, 0.0, -100.0], "spread_m": 25.0, "wingspan_m": 1.2},
            "aircraft": [{"p0_ned_m": [1500.0, -60.0, -160.0], "v_ned_mps": [0.0, 20.0, 0.0]}],
            "glints": [{"p_ned_m": [60.0, 8.0, 0.0], "flicker_depth": 0.0}],
        }
    }
    sc, r = scene(cfg)
    p, R = np.array([0.0, 0.0, -100.0]), look_at(np.array([0.0, 0.0, -100.0]), np.array([100.0, 0.0, -80.0]))
    f, sig = _signal(sc, r, 0.0, p, R)
    ids = [lab.object_id for lab in f.labels]
    assert ids == list(range(1, 7)) and [lab.cls for lab in f.labels] == ["bird"] * 4 + ["aircraft", "glint"]
    checked = 0
    for lab in f.labels:
        if lab.visibility != "visible" or lab.box_px is None:
            continue
        x0, y0, x1, y1 = lab.box_px
        x0, y0, x1, y1 = max(x0 - 2, 0), max(y0 - 2, 0), min(x1 + 2, 640), min(y1 + 2, 512)
        w = np.abs(sig[y0:y1, x0:x1]).astype(float)
        ii, jj = np.mgrid[y0:y1, x0:x1]
        u, v = (w * (jj + 0.5)).sum() / w.sum(), (w * (ii + 0.5)).sum() / w.sum()
        tol = CENTROID_TOL_PX if lab.cls != "aircraft" else 1.5  # the engines pull an aircraft's centroid
        assert math.hypot(u - lab.u_px, v - lab.v_px) < tol, lab
        assert lab.contrast_netd > 3.0
        checked += 1
    assert checked >= 4


def test_bird_flapping_modulates_its_signal_and_glint_flickers():
    cfg = {
        "distractors": {
            "birds": {
                "count": 1,
                "center_ned_m": [60.0, 0.0, -100.0],
                "spread_m": 0.0,
                "speed_mps": 0.0,
                "flap_hz": 2.0,
            },
            "glints": [{"p_ned_m": [1500.0, 0.0, 0.0], "flicker_hz": 1.0, "flicker_depth": 0.8}],
        }
    }
    sc, r = scene(cfg)
    p = np.array([0.0, 0.0, -100.0])
    bird = sc.objects(0.0)[0]
    R = look_at(p, bird.p_ned_m)
    flux, glint = [], []
    for k in range(16):
        t = k / 32.0  # one flap cycle, half a flicker cycle
        f, sig = _signal(sc, r, t, p, R)
        b = f.labels[0]
        flux.append(float(np.abs(sig[int(b.v_px) - 15 : int(b.v_px) + 15, int(b.u_px) - 15 : int(b.u_px) + 15]).sum()))
        glint.append(f.labels[1].contrast_netd)
    assert max(flux) / min(flux) > 1.3  # wings spread vs folded
    assert max(glint) / max(min(glint), 1e-9) > 2.0


def test_out_of_frame_and_behind_camera_labels():
    cfg = {"distractors": {"aircraft": [{"p0_ned_m": [-2000.0, 0.0, -300.0]}, {"p0_ned_m": [2000.0, 3000.0, -100.0]}]}}
    sc, _ = scene(cfg)
    f = sc.render(0.0, np.array([0.0, 0.0, -100.0]), looking(0.0, yaw_deg=0.0), None, None, 0.0)
    behind, aside = f.labels
    assert behind.visibility == "out_of_frame" and math.isnan(behind.u_px) and behind.box_px is None
    assert aside.visibility == "out_of_frame" and aside.u_px > 640


# ---------------------------------------------------------------------------- clutter


def test_point_detector_finds_clutter_in_clouds_and_terrain_none_on_the_clean_sky():
    """15 x 15 local mean, 5 sigma of the temporal noise, blobs <= 50 px (groundsim.world.render.clutter)."""
    per_frame = {}
    for name, raw, h, pitch in [
        ("clean", {}, 100.0, 8.0),
        ("clouds", {"clouds": {"enabled": True}}, 100.0, 8.0),
        ("terrain", {"terrain": {"enabled": True}}, 200.0, -30.0),
    ]:
        sc, r = scene(raw, seed=2)
        counts = []
        for k in range(4):
            p = np.array([6.0 * k, 2.0 * k, -h])
            img = r.quantise(sc.render(k / 30.0, p, looking(pitch, 20.0 + k), None, None, 0.0).radiance)
            counts.append(len(point_detections(img, r.noise_sigma_grey)))
        per_frame[name] = np.mean(counts)
    print("false point-like objects per frame:", per_frame)
    assert per_frame["clean"] <= 0.25
    assert per_frame["clouds"] >= 5.0 and per_frame["terrain"] >= 5.0


# ---------------------------------------------------------------------------- the renderer's hook


def test_render_radiance_on_todays_background_is_render_and_a_cloud_in_front_dims_the_target():
    """The hook draws the target as render() does; a nearer cloud of opacity alpha leaves 1 - alpha of it."""
    p = np.array([0.0, 0.0, -80.0])
    R = looking(5.0)
    p_t = p + R @ np.array([0.02, -0.01, 1.0]) * 120.0
    R_t = rotmat_from_quat(quat_from_euler(0.1, 0.2, 0.3))
    r1 = IrRenderer(INTR, IrSettings(encoding="mono16"), seed=4)
    r2 = IrRenderer(INTR, IrSettings(encoding="mono16"), seed=4)
    today = r1.render(p, R, p_t, R_t, 0.0).astype(int)
    base = r2.base_radiance(p, R, 0.0)
    bg = SceneBackground(base, base, np.full(base.shape, FAR_M, np.float32), np.zeros_like(base))
    L, roi = r2.render_radiance(p, R, p_t, R_t, bg)
    hooked = r2.quantise(L).astype(int)
    assert roi is not None and np.max(np.abs(today - hooked)) <= 1
    assert np.array_equal(bg.radiance, base)  # the background is not modified
    alpha = 0.75
    cloud = SceneBackground(base, base, np.full(base.shape, 60.0, np.float32), np.full(base.shape, alpha, np.float32))
    L_behind, roi_behind = r2.render_radiance(p, R, p_t, R_t, cloud)
    np.testing.assert_allclose(roi_behind[2], (1.0 - alpha) * roi[2], rtol=1e-5, atol=1e-6)
    far_cloud = SceneBackground(base, base, np.full(base.shape, 500.0, np.float32), cloud.cloud_alpha)
    _, roi_front = r2.render_radiance(p, R, p_t, R_t, far_cloud)
    np.testing.assert_array_equal(roi_front[2], roi[2])
    with pytest.raises(InputError, match="background"):
        r2.render_radiance(p, R, p_t, R_t, base)


def test_lens_distortion_depth_follows_each_pixels_ray():
    """With a distorted lens the cloud layer is intersected along each pixel's own (undistorted) ray."""
    distorted = replace(INTR, distortion=(-0.2, 0.05, 0.0, 0.0, 0.0))
    r = IrRenderer(distorted, IrSettings(encoding="mono16"), seed=1)
    sc = SceneContent.from_config(scene_config_from_dict(CLOUDS), r, 3)
    p = np.array([0.0, 0.0, -100.0])
    bg = sc.render_background(p, looking(90.0), 0.0)
    for i, j in ((256, 320), (60, 60), (450, 580)):
        ray = distorted.bearing_cam_from_pixel(np.array([j + 0.5, i + 0.5]))
        assert bg.depth_m[i, j] == pytest.approx(1100.0 / ray[2], rel=DEPTH_RTOL)


@pytest.mark.parametrize("cfg", [{}, CLOUDS, {**CLOUDS, "terrain": TERRAIN["terrain"]}], ids=["sky", "clouds", "both"])
def test_background_and_copy_draws_as_render_background_and_a_copy_do(cfg):
    """``render``'s path (the background's radiance and the copy drawn on written in one pass) against the
    public one (``render_background``, ``draw_objects`` copying), bit for bit; the background is not drawn on."""
    sc, _ = scene(cfg)
    p, R = np.array([0.0, 0.0, -300.0]), looking(4.0)
    objs = (sc.target_object(p + R @ np.array([0.02, 0.01, 1.0]) * 200.0, np.eye(3)),)
    bg, copy = sc.background_and_copy(p, R, 0.0)
    ref = sc.render_background(p, R, 0.0)
    assert np.array_equal(bg.radiance, ref.radiance) and np.array_equal(copy, ref.radiance)
    assert not np.shares_memory(copy, bg.radiance)
    before = bg.radiance.copy()
    drawn, labels = sc.draw_objects(bg.radiance, bg, objs, p, R, out=copy)
    want, want_labels = sc.draw_objects(ref.radiance, ref, objs, p, R)
    assert drawn is copy and np.array_equal(drawn, want) and labels == want_labels
    assert np.array_equal(bg.radiance, before) and not np.array_equal(drawn, before)  # the target is drawn
    with pytest.raises(InputError, match="out"):
        sc.draw_objects(bg.radiance, bg, objs, p, R, out=np.zeros((4, 4), np.float32))
