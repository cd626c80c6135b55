"""Pages written from code must match what the code writes now."""

from __future__ import annotations

from generator.flight.coeffs import CoefficientSet
from generator.report.chain_doc import EXAMPLE, OUT, chain_markdown


def test_chain_page_is_up_to_date():
    want = chain_markdown(CoefficientSet.load(EXAMPLE))
    assert OUT.read_text() == want, "docs/chain.md is stale: run python3 -m generator.report.chain_doc"


def test_chain_page_lists_every_block_of_every_sensor():
    cs = CoefficientSet.load(EXAMPLE)
    text = OUT.read_text()
    for s in cs.unit.sensors:
        assert f"### {s.name} (" in text
        for b in cs.spec.sensor_blocks(s):
            assert f"`{b.name}`" in text
