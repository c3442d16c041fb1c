"""``touchreal bench builds``: simulate, fit and evaluate each build; the table shows what evaluate
measured on the build's held-out trials (a tiny calibration set and a short search here), and the
build's profile and the policy's rules it met, from the fit's provenance."""

from __future__ import annotations

import json

import pytest

from touchreal.cli import main
from touchreal.fitting.describe import rule_summary
from touchreal.fitting.policy import RULES
from touchreal.settings import CLASSES


@pytest.mark.slow  # ~22 s: simulates, fits and evaluates two builds; .ci/run runs it (pytest -m slow)
def test_each_build_row_is_its_own_fit_scored_on_its_held_out_trials(tmp_path, capsys):
    recipe = tmp_path / "short.json"
    recipe.write_text(json.dumps({"generations": 2, "popsize": 4}))
    assert main(["bench", "builds", "--builds", "nominal,noisy-amplifier", "--trials", "ramp=24,sine=10",
                 "--fit-args", f"--recipe {recipe}", "--work", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line.startswith("   ") and "m " in line}
    assert set(rows) == {"nominal", "noisy-amplifier"}
    for build, cells in rows.items():
        manifest = json.loads((tmp_path / build / "manifest.json").read_text())
        assert manifest["simulator"]["build"]["name"] == build  # each build simulated as itself
        prov = json.loads((tmp_path / f"{build}.json").read_text())["provenance"]  # its own parameter file
        assert cells[2:4] == [f"{prov['profile']['contact_snr']:.1f}", f"{1000 * prov['profile']['st_noise_n']:.1f}"]  # the fit's profile
        noisy = build == "noisy-amplifier"  # 3x the PVDF noise (a weak signal) and 2x the SingleTact noise
        assert prov["rules"] == (["weak-signal", "noisy-singletact"] if noisy else []) and cells[-1] == (",".join(prov["rules"]) or "-")
        assert prov["plan"]["gate_factor"] == (2.0 if noisy else 3.0) and prov["plan"]["classes"]["SA1"]["saturated_starts"] == ([-2.0] if noisy else [])
        metrics = json.loads((tmp_path / f"{build}-report" / "metrics.json").read_text())
        for i, c in enumerate(CLASSES):
            s = metrics["mapping"][c]["all"]
            count, vr = cells[4 + 2 * i], cells[5 + 2 * i]
            assert count == f"{s['count_error_mean']:.1%}" and vr == f"{s['ratio_inter_intra']:.2f}", (build, c)
    assert all(f"  {rule_summary(r)}" in out.splitlines() for r in RULES)  # the legend is the policy's table
    assert "every build within the targets:" in out
