"""The example Python client (examples/client.py, as in the README) runs against a real `nak serve`."""

from __future__ import annotations

import client
import numpy as np


def test_python_client_reads_a_full_field_and_the_grasp_force(nak_server: str) -> None:
    answer = client.main(nak_server, "kelvinlet")
    u = answer.displacements
    assert u.shape[1] == 3 and u.shape[0] > 9_500
    # Grasp region 4 is lifted by 2 cm: the largest displacement is about that.
    largest = float((u**2).sum(axis=1).max() ** 0.5)
    assert 0.019 < largest < 0.021
    # The Kelvinlet estimates the force of its one grasper: upwards, like the lift.
    assert answer.grasp_forces is not None and answer.grasp_forces.shape == (1, 3)
    assert answer.grasp_forces[0, 1] > 0.0


def test_python_client_asks_the_best_shipped_network_by_default(nak_server: str) -> None:
    answer = client.main(nak_server)
    u = answer.displacements
    assert answer.grasp_forces is None  # networks give no forces
    assert u.shape[1] == 3 and u.shape[0] > 9_500 and np.isfinite(u).all()
    # A network does not pin the grasped nodes exactly, but lifts the region by about 2 cm.
    largest = float((u**2).sum(axis=1).max() ** 0.5)
    assert 0.01 < largest < 0.04, largest
