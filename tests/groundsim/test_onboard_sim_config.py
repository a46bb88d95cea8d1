"""config/onboard_sim.yaml is config/onboard.yaml with exactly the reference scenarios' camera and a loopback
zenoh listener: the simulator and the daemon agree on the camera, and the noise model is the shipped one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from groundsim.evaluation.eval import onboard_config_for
from groundsim.world.scenario import load_scenario, scenarios_dir
from onboard.app.config import config_to_dict, load_config

REPO = Path(__file__).resolve().parents[2]


def test_onboard_sim_differs_from_the_shipped_config_only_in_camera_and_zenoh_listen():
    shipped = config_to_dict(load_config(REPO / "config/onboard.yaml", environ={}))
    sim = config_to_dict(load_config(REPO / "config/onboard_sim.yaml", environ={}))
    differing = {k for k in shipped if shipped[k] != sim[k]}
    assert differing == {"camera", "zenoh"}
    assert {k for k in shipped["zenoh"] if shipped["zenoh"][k] != sim["zenoh"][k]} == {"listen"}
    assert sim["estimator"] == shipped["estimator"]  # the daemon's shipped noise model


def test_onboard_sim_camera_is_the_reference_scenarios_camera():
    sim = load_config(REPO / "config/onboard_sim.yaml", environ={}).camera
    shipped = load_config(REPO / "config/onboard.yaml", environ={})
    for name in ("P1", "P2", "P3"):
        want = onboard_config_for(load_scenario(scenarios_dir() / f"{name}.yaml"), shipped).camera
        K, K0 = sim.pinhole(), want.pinhole()
        assert (K.fx_px, K.fy_px, K.cx_px, K.cy_px, K.width_px, K.height_px) == pytest.approx(
            (K0.fx_px, K0.fy_px, K0.cx_px, K0.cy_px, K0.width_px, K0.height_px), abs=1e-9
        ), name
        m, m0 = sim.camera_mount(), want.camera_mount()
        np.testing.assert_allclose(m.lever_arm_frd_m, m0.lever_arm_frd_m, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(
            np.abs(np.dot(m.q_body_from_mount, m0.q_body_from_mount)), 1.0, atol=1e-12, err_msg=name
        )
        assert m.gimballed == m0.gimballed is True, name


def _body(path: Path) -> list[str]:
    """The file's lines after its header comment, blank lines left out."""
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    start = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    return lines[start:]


def test_onboard_sim_is_the_shipped_file_line_for_line_but_its_sim_lines():
    """The file a newcomer runs first says what config/onboard.yaml says, comments included: a comment added to one
    (camera.intrinsics' zoom, say) and not to the other drifts apart unseen by the value checks above."""
    shipped, sim = _body(REPO / "config/onboard.yaml"), _body(REPO / "config/onboard_sim.yaml")
    assert len(shipped) == len(sim)
    differing = [(a, b) for a, b in zip(shipped, sim, strict=True) if a != b]
    assert differing and all("(sim)" in b for _, b in differing), [b for _, b in differing if "(sim)" not in b]
