"""``touchreal bench builds``: simulate, fit and evaluate each build; the table shows what evaluate
measured on the build's held-out trials (a tiny calibration set and a short search here)."""

from __future__ import annotations

import json

from touchreal.cli import main
from touchreal.settings import CLASSES


def test_each_build_row_is_its_own_fit_scored_on_its_held_out_trials(tmp_path, capsys):
    assert main(["bench", "builds", "--builds", "nominal,noisy-amplifier", "--trials", "ramp=24,sine=10",
                 "--fit-args", "--generations 2 --popsize 4", "--work", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line.startswith("   ") and "m " in line}
    assert set(rows) == {"nominal", "noisy-amplifier"}
    for build, cells in rows.items():
        manifest = json.loads((tmp_path / build / "manifest.json").read_text())
        assert manifest["simulator"]["build"]["name"] == build  # each build simulated as itself
        prov = json.loads((tmp_path / f"{build}.json").read_text())["provenance"]  # its own parameter file
        assert cells[2] == f"{prov['contact_snr']:.0f}" + ("*" if build == "noisy-amplifier" else "")  # the fit's SNR
        assert prov["gate_factor"] == (2.0 if build == "noisy-amplifier" else 3.0)  # the noisy one fitted as weak-signal
        noisy = build == "noisy-amplifier"  # 2x the SingleTact noise: SA1's noisy-SingleTact search
        assert cells[3] == f"{1000 * prov['st_noise_n']:.1f}" + ("*" if noisy else "") and prov["noisy_singletact"] == noisy
        assert prov["optimizer"]["saturated_classes"] == (["SA1"] if noisy else [])
        metrics = json.loads((tmp_path / f"{build}-report" / "metrics.json").read_text())
        for i, c in enumerate(CLASSES):
            s = metrics["mapping"][c]["all"]
            count, vr = cells[4 + 2 * i], cells[5 + 2 * i]
            assert count == f"{s['count_error_mean']:.1%}" and vr == f"{s['ratio_inter_intra']:.2f}", (build, c)
    assert "every build within the targets:" in out
