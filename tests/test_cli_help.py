"""Every subcommand's help reads as a user's: every option explained, defaults printed
as values (never as ``config.NAME``)."""

import argparse

from bigT.cli import build_parser


def _subparsers():
    parser = build_parser()
    group = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return group.choices


def test_every_subcommand_help_is_complete():
    subs = _subparsers()
    assert {"demo", "scene", "invert", "compensate", "relight", "bounces", "convert",
            "export", "info"} <= set(subs)
    for name, sub in subs.items():
        text = sub.format_help()
        assert "config." not in text, name
        for action in sub._actions:
            if action.option_strings and action.dest != "help":
                assert action.help, f"bigT {name} {action.option_strings[0]} has no help"
