"""The network items of ``slamtka bench hardening``, small counts, against the real SCP."""

from __future__ import annotations

import pytest

from slamtka.bench.hardening import run_items
from slamtka.bench.network import NETWORK_ITEMS
from slamtka.service.compressed import encoders_available

SMALL = {"tls_names": 1, "ae_squatting": 2, "compressed": 1, "pixel_layouts": 1}


@pytest.mark.parametrize("item", NETWORK_ITEMS)
def test_network_item_has_no_failures(tmp_path, item):
    if item == "compressed" and not encoders_available():
        pytest.skip("DCMTK not installed")
    result = run_items(tmp_path, {item: SMALL[item]})[item]
    assert result["tried"] >= 4 and result["failures"] == 0, result
