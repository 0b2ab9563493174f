"""Bad command-line arguments, generated from every (sub)command's own parser: each value an option or a
positional argument converts (numbers, ids, words) given nan, infinities, -1, 1e308, nothing and a word; each
choice given a wrong one; each command given an option it does not have. Each is refused with one line naming the
argument, before anything starts."""

from __future__ import annotations

import argparse

import pytest

from cli.bad_input.cases import actions, name, parsers, positional_values, positionals, typed
from cli.bad_input.harness import check

BAD_VALUES = {"nan": "nan", "inf": "inf", "-inf": "-inf", "-1": "-1", "1e308": "1e308", "empty": "", "word": "abc"}


def _value_cases() -> list:
    cases = []
    for path, parser in parsers():
        given = positional_values(path, parser)
        for action in typed(parser):
            for label, value in BAD_VALUES.items():
                if action.option_strings:
                    argv = [*path, f"{action.option_strings[0]}={value}", *given]
                else:  # replace this positional's value; '--' so that '-1' and '-inf' are values
                    index = positionals(path, parser).index(action)
                    values = list(given) + [""] * (index + 1 - len(given))
                    values[index] = value
                    argv = [*path, "--", *values]
                cases.append(pytest.param(argv, name(action), id=f"{' '.join(path)} {name(action)}={label}"))
    return cases


def _choice_cases() -> list:
    cases = []
    for path, parser in parsers():
        given = positional_values(path, parser)
        for action in actions(parser):
            if action.choices is None or not action.option_strings or action.help == "==SUPPRESS==":
                continue
            for label, value in (("empty", ""), ("unknown", "bogus")):
                cases.append(pytest.param([*path, f"{action.option_strings[0]}={value}", *given], name(action),
                                          id=f"{' '.join(path)} {name(action)}={label}"))
    return cases


def _unknown_option_cases() -> list:
    return [pytest.param([*path, "--no-such-option", *positional_values(path, parser)], "--no-such-option",
                         id=" ".join(path)) for path, parser in parsers()]


def _missing_positional_cases() -> list:
    cases = []
    for path, parser in parsers():
        required = [a for a in positionals(path, parser) if a.nargs != "?"]
        if required:
            cases.append(pytest.param(list(path), name(required[0]), id=" ".join(path)))
    return cases


@pytest.mark.parametrize("argv, names", _value_cases())
def test_a_bad_value_is_one_line_naming_the_argument(folder, monkeypatch, argv, names):
    check(argv, folder, monkeypatch, needles=(names,))


@pytest.mark.parametrize("argv, names", _choice_cases())
def test_a_choice_not_offered_is_one_line_naming_the_option(folder, monkeypatch, argv, names):
    check(argv, folder, monkeypatch, needles=(names,))


@pytest.mark.parametrize("argv, names", _unknown_option_cases())
def test_an_option_the_command_has_not_is_one_line_naming_it(folder, monkeypatch, argv, names):
    check(argv, folder, monkeypatch, needles=(names,))


@pytest.mark.parametrize("argv, names", _missing_positional_cases())
def test_a_missing_argument_is_one_line_naming_it(folder, monkeypatch, argv, names):
    check(argv, folder, monkeypatch, needles=(names,))


def _defaulted_options() -> list:
    cases = []
    for path, parser in parsers():
        for action in actions(parser):
            if (action.option_strings and action.help not in (None, argparse.SUPPRESS) and action.default is not None
                    and action.default is not argparse.SUPPRESS and not isinstance(action.default, bool)
                    and action.nargs != 0):
                cases.append(pytest.param(action, id=f"{' '.join(path)} {action.option_strings[0]}"))
    return cases


@pytest.mark.parametrize("action", _defaulted_options())
def test_every_option_with_a_default_says_it_in_its_help(action):
    assert "default" in action.help, f"{action.option_strings[0]}: {action.help!r} does not give its default"
