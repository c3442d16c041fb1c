"""The command line on bad input and edge cases (issue 20, point 7): one clear line, a non-zero exit,
never a traceback; and the cases that used to crash now run."""

from __future__ import annotations

import subprocess
import sys

import pytest

from touchreal.cli import main


def one_error_line(capsys, command: str) -> str:
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip() and "%|" not in x]  # progress bars aside
    assert len(err) == 1 and err[0].startswith(f"touchreal {command}: error: "), err
    return err[0]


def test_bench_encoder_runs_with_fewer_taxels_than_the_demand_table_used_to_assume(capsys):
    assert main(["bench", "encoder", "--taxels", "4", "--seconds", "0.3", "--latency-seconds", "0.3",
                 "--skip-sweep"]) == 0
    out = capsys.readouterr().out
    assert "4 taxels, all classes" in out and "nobody (acquisition only)" in out
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "encoder", "--taxels", "0,4"])
    assert exit_.value.code == 2 and "taxel counts must be in 1..4096" in capsys.readouterr().err


def test_decoders_evaluate_without_held_out_trials_fails_clearly(tmp_path, capsys):
    assert main(["simulate", "texture", "--out", str(tmp_path / "tex"), "--trials", "1"]) == 0
    capsys.readouterr()
    code = main(["decoders", "evaluate", str(tmp_path / "tex"), "--tasks", "texture", "--out", str(tmp_path / "m.json"),
                 "--quiet"])
    assert code == 2 and not (tmp_path / "m.json").exists()
    assert "no texture trials in the heldout split" in one_error_line(capsys, "decoders")


def test_fit_on_dask_without_the_extra_prints_the_install_hint(tmp_path):
    code = ("import sys; sys.modules['distributed'] = None\n"  # as if the fit-dask extra were not installed
            "from touchreal.cli import main\n"
            f"raise SystemExit(main(['fit', {str(tmp_path)!r}, '--out', {str(tmp_path / 'p.json')!r}, "
            "'--dask-workers', '2']))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "pip install -e '.[fit-dask]'" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("argv, words", [
    (["encode", "/nonexistent/ds", "--params", "/nonexistent/p.json", "--out", "/tmp/x"], "/nonexistent"),
    (["evaluate", "/nonexistent/ds", "--params", "/nonexistent/p.json", "--out", "/tmp/x"], "/nonexistent"),
])
def test_bad_paths_are_one_line(argv, words, capsys):
    assert main(argv) != 0
    assert words in one_error_line(capsys, argv[0])
