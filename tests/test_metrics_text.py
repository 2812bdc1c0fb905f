"""Reading a /metrics page (the benches scrape services): a series is found by its name
and labels in any order. bench_team looked up ``hivemap_stored_total`` with its labels
in declaration order (service, kind), the client library writes them sorted (kind,
service), and its per-mapper table read 0 keyframes stored for every mapper."""

from __future__ import annotations

from prometheus_client import REGISTRY, generate_latest

from shared.metrics import STORED, parse_exposition, sample_value, series_key


def test_a_scraped_series_is_found_whatever_order_its_labels_are_named_in():
    STORED.labels("mapper", "keyframe").inc(3)
    page = parse_exposition(generate_latest(REGISTRY).decode())
    want = sample_value("hivemap_stored_total", {"service": "mapper", "kind": "keyframe"})
    assert want >= 3
    for labels in ({"service": "mapper", "kind": "keyframe"},
                   {"kind": "keyframe", "service": "mapper"}):  # fmt: skip
        assert page[series_key("hivemap_stored_total", labels)] == want
    text = '# HELP x_total X\nx_total{b="1,2",a="say \\"hi\\""} 3.0\ny 4\nz{le="+Inf"} 5\n'
    page = parse_exposition(text)
    assert page[series_key("x_total", {"a": 'say \\"hi\\"', "b": "1,2"})] == 3.0
    assert page["y"] == 4.0 and page[series_key("z", {"le": "+Inf"})] == 5.0
