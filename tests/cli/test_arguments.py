"""Option values checked while parsing (``tactile_slam.cli.arguments``): a bad output
location or number stops a command before any work, with a message naming the option."""

from __future__ import annotations

import argparse
import os

import numpy as np
import pytest
import torch

from tactile_slam.cli.arguments import (
    non_negative_float,
    output_file,
    output_file_or_stdout,
    output_folder,
    positive_int,
    positive_int_list,
)
from tactile_slam.cli.main import main


@pytest.fixture
def a_file(tmp_path):
    path = tmp_path / "taken"
    path.write_text("x")
    return path


class TestOutputFolder:
    def test_smoke(self, tmp_path):
        assert output_folder(str(tmp_path)) == str(tmp_path)  # an existing folder
        assert output_folder(str(tmp_path / "new" / "deeper")) == str(tmp_path / "new" / "deeper")  # made later
        assert not (tmp_path / "new").exists()  # checking creates nothing

    def test_exceptions(self, tmp_path, a_file):
        with pytest.raises(argparse.ArgumentTypeError, match="is an existing file"):
            output_folder(str(a_file))
        with pytest.raises(argparse.ArgumentTypeError, match=f"{a_file} is a file, not a folder"):
            output_folder(str(a_file / "sub" / "run"))
        with pytest.raises(argparse.ArgumentTypeError, match="empty path"):
            output_folder("")

    @pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
    def test_read_only_parent(self, tmp_path):
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o555)
        try:
            with pytest.raises(argparse.ArgumentTypeError, match="no permission to write"):
                output_folder(str(locked / "run"))
        finally:
            locked.chmod(0o755)


class TestOutputFile:
    def test_smoke(self, tmp_path, a_file):
        assert output_file(str(a_file)) == str(a_file)  # replaced later
        assert output_file(str(tmp_path / "sub" / "x.json")) == str(tmp_path / "sub" / "x.json")
        assert output_file_or_stdout("-") == "-"
        assert output_file_or_stdout(str(a_file)) == str(a_file)

    def test_exceptions(self, tmp_path, a_file):
        with pytest.raises(argparse.ArgumentTypeError, match="is an existing folder"):
            output_file(str(tmp_path))
        with pytest.raises(argparse.ArgumentTypeError, match="is a file, not a folder"):
            output_file(str(a_file / "x.json"))
        with pytest.raises(argparse.ArgumentTypeError, match="is an existing folder"):
            output_file_or_stdout(str(tmp_path))


class TestNumbers:
    @pytest.mark.parametrize("text, value", [("1", 1), ("16", 16)])
    def test_positive_int(self, text, value):
        assert positive_int(text) == value

    @pytest.mark.parametrize("text", ["0", "-2", "1.5", "two", ""])
    def test_positive_int_refuses(self, text):
        with pytest.raises(argparse.ArgumentTypeError):
            positive_int(text)

    def test_positive_int_list(self):
        assert positive_int_list("32,32,32") == (32, 32, 32)
        assert positive_int_list("64") == (64,)
        for bad in ("", "32,", "0,8", "a,b"):
            with pytest.raises(argparse.ArgumentTypeError, match="comma-separated integers"):
                positive_int_list(bad)

    @pytest.mark.parametrize("text, value", [("0", 0.0), ("2.5", 2.5), ("1e-3", 1e-3)])
    def test_non_negative_float(self, text, value):
        assert non_negative_float(text) == value

    @pytest.mark.parametrize("text", ["-1", "-1e-9", "nan", "inf", "-inf", "fast"])
    def test_non_negative_float_refuses(self, text):
        with pytest.raises(argparse.ArgumentTypeError):
            non_negative_float(text)


def _parse_error(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize("command", [
    ["run", "SCAN", "--out"], ["simulate", "--out"], ["demo", "--out"], ["record", "SOURCE", "--out"],
    ["live", "--out"], ["calibrate", "train", "CALIB", "--out"], ["calibrate", "label", "CALIB", "--out"],
])
def test_commands_refuse_a_file_as_output_folder(command, a_file, capsys):
    """Every command that writes a folder refuses an existing file before reading its
    input (SCAN, SOURCE and CALIB do not exist: the output is checked first)."""
    err = _parse_error([*command, str(a_file)], capsys)
    assert f"argument --out: output folder {a_file} is an existing file" in err


def test_bench_refuses_a_json_path_under_a_file(a_file, capsys):
    err = _parse_error(["bench", "geometry", "--out", str(a_file / "geometry.json")], capsys)
    assert "argument --out: output file" in err and "is a file, not a folder" in err


@pytest.mark.parametrize("option, value, message", [
    ("--threads", "0", "argument --threads: must be >= 1, got 0"),
    ("--batch-size", "0", "argument --batch-size: must be >= 1, got 0"),
    ("--rate", "-1", "argument --rate: must be a finite number >= 0"),
    ("--rate", "nan", "argument --rate: must be a finite number >= 0"),
    ("--buffer-frames", "0", "argument --buffer-frames: must be >= 1"),
    ("--preview-every", "-1", "argument --preview-every: must be a finite number >= 0"),
])
def test_run_refuses_bad_numbers(tmp_path, capsys, option, value, message):
    assert message in _parse_error(["run", "SCAN", "--out", str(tmp_path / "o"), "--online", option, value], capsys)


@pytest.fixture
def short_sequence(tmp_path):
    """Eight frames of a textureless touch: enough for a run, no ground truth needed."""
    h, w = 240, 320
    y, x = np.mgrid[0:h, 0:w]
    contact = np.zeros((8, h, w), bool)
    contact[2:] = (x - w / 2) ** 2 + (y - h / 2) ** 2 < 80 ** 2
    path = tmp_path / "flat.npz"
    np.savez(path, gradients=np.zeros((8, h, w, 2), np.float32), contact=contact)
    return path


def test_run_refuses_online_options_without_online(short_sequence, tmp_path, capsys):
    """Options that only the online pipeline reads are refused offline instead of being
    ignored, and nothing is written."""
    out = tmp_path / "o"
    assert main(["run", str(short_sequence), "--out", str(out), "--rate", "2", "--jsonl", "-"]) == 2
    assert "--rate, --jsonl: used only with --online" in capsys.readouterr().err
    assert not out.exists()


def test_offline_run_uses_the_threads_option(short_sequence, tmp_path):
    """``run --threads N`` without ``--online`` sets torch's threads for the run (it was
    ignored offline)."""
    n = torch.get_num_threads() + 1
    assert main(["run", str(short_sequence), "--out", str(tmp_path / "o"), "--no-mesh", "--no-progress",
                 "--method", "nf-kf", "--threads", str(n)]) == 0
    assert torch.get_num_threads() == n
    assert (tmp_path / "o" / "poses.npy").exists()


@pytest.mark.parametrize("argv", [
    ["bench", "registration", "--repeats", "0"], ["bench", "tracking", "--frames", "0"],
    ["bench", "loops", "--sizes", "100", "0"], ["bench", "posegraph", "--keyframes", "-5"],
    ["bench", "reconstruction", "--touches", "0"], ["eval", "RUN", "--gt", "EP", "--samples", "0"],
])
def test_counts_below_one_are_parse_errors(argv, tmp_path, capsys):
    """Repeat, frame, size and sample counts of the benches and ``eval`` are >= 1 (``eval
    --samples 0`` used to score meshes from no samples at all)."""
    assert "must be >= 1" in _parse_error(argv, capsys)
