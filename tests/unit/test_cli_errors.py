"""How the openfusion command reports errors, in this process: a user error is one line and exit
code 2, a bug keeps its traceback, OPENFUSION_DEBUG=1 shows every traceback."""

from __future__ import annotations

import pytest

from openfusion.app import cli
from openfusion.sources.base import SourceError

pytestmark = pytest.mark.timeout(120)


class _FailingCommand:
    """A subcommand whose library call refuses bad input (a UserError) or hits a bug."""

    @staticmethod
    def add_arguments(parser) -> None:
        parser.add_argument("--spec", default="nosuch:/x")
        parser.add_argument("--bug", action="store_true")

    @staticmethod
    def run(args) -> int:
        if args.bug:
            raise KeyError("a bug")
        raise SourceError(f"unknown source scheme in {args.spec!r}")


def test_user_errors_are_one_line_exit_2_and_bugs_keep_their_traceback(monkeypatch, capsys) -> None:
    """A UserError from library code (bad user input) ends as one stderr line and exit code 2;
    OPENFUSION_DEBUG=1 brings the traceback back; an exception outside the package's error tree
    (a bug) is not swallowed into one line."""
    monkeypatch.setattr(cli, "SUBCOMMANDS", [cli.Subcommand("failing", f"{__name__}:_FailingCommand", "fails")])
    monkeypatch.delenv("OPENFUSION_DEBUG", raising=False)
    assert cli.main(["failing"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["openfusion failing: error: unknown source scheme in 'nosuch:/x'"]
    with pytest.raises(KeyError, match="a bug"):
        cli.main(["failing", "--bug"])
    monkeypatch.setenv("OPENFUSION_DEBUG", "1")
    with pytest.raises(SourceError, match="unknown source scheme"):
        cli.main(["failing"])
