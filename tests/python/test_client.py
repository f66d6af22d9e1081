"""The README's Python client runs against a real `nak serve`."""

from __future__ import annotations

import client


def test_python_client_reads_a_full_field(nak_server: str) -> None:
    u = client.main(nak_server)
    assert u.shape[1] == 3 and u.shape[0] > 9_500
    # Grasp region 4 is lifted by 2 cm: the largest displacement is about that.
    largest = float((u**2).sum(axis=1).max() ** 0.5)
    assert 0.019 < largest < 0.021
