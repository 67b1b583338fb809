"""The command line's own kind of option and command: an option keeps its old spellings as hidden
aliases and names the heading it is listed under in ``--help``; a command lists its options under
those headings.

The vocabulary (docs/guide/command_names.md has the table of renames): one name per idea on
every command, its unit as a suffix where it has one (``--length-m``, ``--lag-s``); ``--max-...`` a
cap (``--max-points``, ``--max-frames``), a plain noun a count (``--frames``, ``--views``,
``--measurements``); a list takes the plural (``--estimators``, ``--seeds``) except the cap on live
points, ``--max-points 150,500``.
"""

from __future__ import annotations

import functools

import click

OTHER = "Other options"  # the heading of a grouped command's options that name none (-h)
_NAME_COLUMN = 30  # click's widest first column; a longer name puts its help on the next line


class Option(click.Option):
    """A :class:`click.Option` with ``old``: earlier spellings, still parsed into the same parameter
    but shown nowhere (not in ``--help``, the command reference or an error message), and
    ``group``: the heading the option is listed under in ``--help`` (:class:`GroupedCommand`)."""

    def __init__(self, *args, old: tuple[str, ...] | str = (), group: str | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.old_spellings = (old,) if isinstance(old, str) else tuple(old)
        self.help_group = group

    def get_help_extra(self, ctx: click.Context):
        """Click's bracketed extras, without the range of a number whose metavar already gives it (``0-63``)."""
        extra = super().get_help_extra(ctx)
        if self.metavar is not None:
            extra.pop("range", None)
        return extra

    def add_to_parser(self, parser, ctx: click.Context) -> None:
        """Register the option under its names and its old spellings, the latter for this parse only."""
        shown = self.opts
        self.opts = [*shown, *self.old_spellings]
        try:
            super().add_to_parser(parser, ctx)
        finally:
            self.opts = shown


option = functools.partial(click.option, cls=Option)
"""``click.option`` making an :class:`Option` (``old=``, ``group=``)."""


class GroupedCommand(click.Command):
    """A command whose ``--help`` lists its options under their :attr:`Option.help_group` headings, in
    the order each heading first appears, the first column as wide as the widest name that fits in
    it, across headings; a command whose options name no heading lists them under ``Options``, as
    click does."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        """Click's parse, an unknown option's "did you mean" naming only the shown names (no old spelling)."""
        try:
            return super().parse_args(ctx, args)
        except click.NoSuchOption as exc:
            shown = [name for p in self.get_params(ctx) if isinstance(p, click.Option) for name in (*p.opts, *p.secondary_opts) if name.startswith("--")]
            raise click.NoSuchOption(exc.option_name, message=exc.message, possibilities=shown, ctx=ctx) from None

    def format_options(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        sections = _option_sections(self, ctx)
        width = max((len(name) for rows in sections.values() for name, _ in rows if len(name) <= _NAME_COLUMN), default=0)
        for heading, rows in sections.items():
            with formatter.section(heading):
                formatter.write_dl([(name.ljust(width), text) for name, text in rows], col_max=width or _NAME_COLUMN)


def _option_sections(command: click.Command, ctx: click.Context) -> dict[str, list[tuple[str, str]]]:
    """The help rows of ``command``'s shown options by heading, in order of first appearance."""
    params = [p for p in command.get_params(ctx) if isinstance(p, click.Option) and p.get_help_record(ctx) is not None]
    grouped = any(getattr(p, "help_group", None) for p in params)
    sections: dict[str, list[tuple[str, str]]] = {}
    for param in params:
        heading = getattr(param, "help_group", None) or (OTHER if grouped else "Options")
        sections.setdefault(heading, []).append(param.get_help_record(ctx))
    if OTHER in sections:  # last, after the headings the command names
        sections[OTHER] = sections.pop(OTHER)
    return sections


class Group(click.Group):
    """A group whose commands are :class:`GroupedCommand` and whose subgroups are of its own class."""

    command_class = GroupedCommand
    group_class = type


def number_list(text: str, kind, what: str) -> tuple:
    """``"0-7"``, ``"1,2,5"`` or ``"1.5"`` as numbers, without repeats; a usage error naming the
    option ``what`` otherwise."""
    out = []
    try:
        for part in (p.strip() for p in text.split(",") if p.strip()):
            if kind is int and "-" in part[1:]:
                lo, hi = part.split("-", 1) if not part.startswith("-") else (part, part)
                out.extend(range(int(lo), int(hi) + 1))
            else:
                out.append(kind(part))
    except ValueError:
        raise click.BadParameter(f"{text!r} is not a list of numbers", param_hint=what) from None
    if not out:
        raise click.BadParameter("give at least one", param_hint=what)
    return tuple(dict.fromkeys(out))


def realtime_option(default: bool, why: str, group: str | None = None):
    """``--realtime/--as-fast-as-possible``, the same pair on every command that replays a log;
    ``why`` says why its default is the one it is."""
    return option(
        "--realtime/--as-fast-as-possible",
        default=default,
        group=group,
        help=f"Feed the events at the sensors' pace (a run lasts the log's duration), or as fast as taken [default: {'realtime' if default else 'as fast as possible'}: {why}].",
    )
