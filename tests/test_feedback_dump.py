"""The opt-in recorder of the feedback loop (HIVEMAP_FEEDBACK_DUMP) for offline replay."""

from __future__ import annotations

import numpy as np

from shared import feedback_dump


def test_off_by_default_and_records_in_order_when_on(tmp_path, monkeypatch):
    monkeypatch.delenv("HIVEMAP_FEEDBACK_DUMP", raising=False)
    feedback_dump.record("off", "x", a=1)
    assert not feedback_dump.enabled() and not list(tmp_path.iterdir())
    monkeypatch.setenv("HIVEMAP_FEEDBACK_DUMP", str(tmp_path / "d"))
    feedback_dump.record("mapper", "fc", T=np.eye(4))
    feedback_dump.record("agent1", "chunk", frame=3)
    recs = feedback_dump.load(tmp_path / "d")
    assert [(r["who"], r["kind"]) for r in recs] == [("mapper", "fc"), ("agent1", "chunk")]
    np.testing.assert_array_equal(recs[0]["T"], np.eye(4))
