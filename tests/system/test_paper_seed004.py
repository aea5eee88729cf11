"""The seed 004 section of ``btmission bench paper`` (quick mode: structure and sane numbers)."""

from __future__ import annotations

import math

from btmission.bench import paper_seed004 as sec
from btmission.bench.paper import SectionResult


def test_quick_section_has_the_tables_and_sane_numbers() -> None:
    lines: list[str] = []
    res = sec.run(True, lines.append)
    assert isinstance(res, SectionResult) and sec.KEY == "seed004"
    md = res.markdown
    for part in ("**Table 6**", "**Tables 2 and 3**", "**Table 5**", "mine_table6",
                 "btmission bench paper --only seed004"):  # fmt: skip
        assert part in md
    # Table 6: one row per fleet size with the paper's C next to ours
    for L, (c, _, _) in sec.TABLE6.items():
        assert f"| {L} | {c} |" in md
        row = res.data["table6"][str(L)]
        assert row["C"] > 0 and 0 <= row["i_t"] < 1 and 0 <= row["i_p"] < 1
    # static: every success rate is a percentage; r >= 1 where defined
    for d in res.data["static"].values():
        assert 0 <= d["sigma"] <= 100
        assert math.isnan(d["r"]) or d["r"] >= 1.0
    # push and swap: one swap per pair one hop back costs 4·1 + 4 = 8 items beyond ξ_min
    for d in res.data["table5"].values():
        if not math.isnan(d["pas_extra_per_pair"]):
            assert d["pas_extra_per_pair"] >= 8.0 - 1e-9
    assert any("static batch NPR" in x for x in lines)
