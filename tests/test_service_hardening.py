"""Hardening, small counts of every item of ``slamtka bench hardening`` against the real SCP.

Each item counts an input as failed if it was acknowledged, its refusal was not audited, it
hung, the server stopped serving, memory grew by 256 MB or more, or (fuzzing) anything in the
spool fails validation again. The bench runs the same items with large counts.
"""

from __future__ import annotations

import pytest

from slamtka.bench.hardening import ITEMS, run_items
from slamtka.bench.hostile import frame_dataset_bytes, nested_sequence, truncations
from slamtka.service.audit import read_audit
from slamtka.service.dataset_guard import DatasetError, check_dataset_bytes

SMALL = {"uids": 37, "truncation": 40, "pixel_length": 7, "element_length": 6, "nesting": 3,
         "deflate": 2, "oversize": 2, "fuzz_datasets": 300, "fuzz_protocol": 300,
         "admission": 1, "tls": 1, "idle_flood": 5, "disk_full": 2}

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.mark.parametrize("item", ITEMS)
def test_item_has_no_failures(tmp_path, item):
    result = run_items(tmp_path, {item: SMALL[item]}, bound_s=10.0)[item]
    assert result["tried"] >= min(SMALL[item], 5)
    assert result["failures"] == 0, result
    if "memory_growth_mb" in result:
        assert result["memory_growth_mb"] < 256


def test_refusals_name_their_reason_in_the_audit_log(tmp_path):
    run_items(tmp_path, {"tls": 1, "oversize": 2})
    tls = {e["reason"] for e in read_audit(tmp_path / "tls" / "audit.jsonl")
           if e["event"] == "connection_refused"}
    assert any("certificate" in r.lower() for r in tls) and len(tls) >= 3
    aborted = [e["reason"] for e in read_audit(tmp_path / "oversize" / "audit.jsonl")
               if e["event"] == "association_aborted"]
    assert any("declares" in r for r in aborted) and any("dropped unread" in r for r in aborted)


def test_the_structural_check_refuses_every_cut_inside_an_element():
    for explicit in (True, False):
        data, _ = frame_dataset_bytes(0, 8, explicit)
        check_dataset_bytes(data, explicit)
        refused = 0
        for cut in truncations(data, 200):
            try:
                check_dataset_bytes(data[:cut], explicit)
            except DatasetError:
                refused += 1
        assert refused >= 180  # the rest end on an element boundary (caught as missing data)
        with pytest.raises(DatasetError, match="nest deeper"):
            check_dataset_bytes(nested_sequence(data, 10_000, explicit), explicit)
