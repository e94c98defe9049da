"""What the CLI's error-path tests share."""

from __future__ import annotations

from psmini.cli import main


def fails_in_one_line(capsys, argv: list[str], *expected: str) -> str:
    """Run ``psmini ARGV``: it must exit 1 with one line on stderr, no traceback, holding every ``expected`` text."""
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    for text in expected:
        assert text in err, err
    return err
