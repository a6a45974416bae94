"""The single entry point: subcommands listed, unknown ones refused in one line."""

import subprocess
import sys

from driftlab.cli import build_parser, main


def test_help_lists_subcommands(capsys):
    parser = build_parser()
    text = parser.format_help()
    assert "COMMAND" in text
    assert main([]) == 2


def test_unknown_subcommand_is_one_line_error():
    proc = subprocess.run([sys.executable, "-m", "driftlab.cli", "frobnicate"], capture_output=True, text=True)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("driftlab: error:")
    assert "frobnicate" in lines[0]
