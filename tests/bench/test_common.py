"""Options shared by the benches."""

import pytest
import torch

from tactile_slam.cli.main import main


@pytest.mark.parametrize("bench,extra", [
    ("loops", ["--objects", "--sizes", "--index-sizes", "--backend-objects"]),
    ("registration", []), ("tracking", []), ("calibration", []),
])
@pytest.mark.parametrize("value", ["0", "-2"])
def test_bad_threads_is_an_error(tmp_path, capsys, bench, extra, value):
    """Every bench with ``--threads`` refuses a count below 1 while parsing, before doing
    any work (it was silently ignored at 0 by some of them)."""
    threads = torch.get_num_threads()
    with pytest.raises(SystemExit) as exc:
        main(["bench", bench, "--out", str(tmp_path / "x.json"), *extra, "--threads", value])
    assert exc.value.code == 2
    assert f"argument --threads: must be >= 1, got {value}" in capsys.readouterr().err
    assert torch.get_num_threads() == threads and not (tmp_path / "x.json").exists()
