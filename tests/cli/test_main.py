"""The ``tactile-slam`` entry point: a native crash still names where it happened."""

import subprocess
import sys
import textwrap


def test_a_native_crash_prints_the_python_stack():
    """A segmentation fault inside a native call (as Open3D once had in a long benchmark)
    ends the process, but the entry point has enabled faulthandler, so stderr shows the
    Python frames that led to it instead of a bare 'Segmentation fault'."""
    script = textwrap.dedent("""
        import argparse, ctypes, sys
        from tactile_slam.cli import main as cli

        def crash_in_native_code(args):
            ctypes.string_at(0)

        def parser():
            p = argparse.ArgumentParser()
            p.set_defaults(func=crash_in_native_code, command="crash")
            return p

        cli.build_parser = parser
        sys.exit(cli.main([]))
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0
    assert "Fatal Python error" in proc.stderr and "crash_in_native_code" in proc.stderr


def test_caveats_name_broken_sessions_and_guessed_depths():
    from tactile_slam.cli.live import caveats

    assert caveats({"sessions": 3, "registration_breaks": 0, "keyframes_depth_unknown": 0}) == []
    assert caveats({"sessions": 1}) == []  # runs whose statistics lack the counters
    lines = caveats({"sessions": 6, "registration_breaks": 5, "keyframes_depth_unknown": 2})
    assert lines[0].startswith("5 of the 6 sessions began inside a contact") and lines[1].startswith("2 keyframes")
