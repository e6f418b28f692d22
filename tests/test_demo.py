"""The simulator demo runs and shows what it claims (few frames, CPU)."""

import numpy as np

from empm_gym.demo import run_sim_demo


def test_sim_demo_writes_outputs_and_lifts_the_rope(tmp_path):
    runs = run_sim_demo(tmp_path, frames=10, progress=False)
    assert (tmp_path / "sim_demo.png").stat().st_size > 10_000
    assert (tmp_path / "sim_demo.rrd").stat().st_size > 10_000
    xs, ees, _, _, _ = runs["rope lifted at one end"]
    # the gripped end follows the gripper (closed gripper = Dirichlet), the far end stays on the table
    gripper = ees[-1][0]
    near = np.linalg.norm(xs[-1] - gripper, axis=1) < 0.03
    assert near.sum() > 10 and gripper[2] > 0.15
    assert xs[-1][:, 0].min() < -0.1 and np.sort(xs[-1][:, 2])[10] < 0.03
    xs, _, _, _, _ = runs["dough squeezed by two grippers"]
    # plastic: the squeezed block stays narrower in x and grows taller after release
    assert np.ptp(xs[-1][:, 0]) < 0.9 * np.ptp(xs[0][:, 0])
    assert xs[-1][:, 2].max() > xs[0][:, 2].max() + 0.005
