"""What a person sees during guided collection: a live rich table on a terminal, plain lines otherwise.

Both take the library's :class:`~ivc.collect.guide.StepStatus` snapshots (``on_status``), the start of each step
(``on_step_start``) and its report (``on_step``); they print and decide nothing.
"""

from __future__ import annotations

import sys
import time

import click

from ivc.collect.guide import StepReport, StepStatus

#: plain output: a progress line at most this often (host seconds), besides every change of problems
PLAIN_EVERY_S = 5.0


def _bar(fraction: float, width: int = 20) -> str:
    filled = int(round(width * max(0.0, min(1.0, fraction))))
    return "#" * filled + "-" * (width - filled)


def _progress_words(status: StepStatus) -> str:
    return "; ".join(f"{p.label} {p.value:,.4g}/{p.target:,.4g} {p.unit}" for p in status.progress)


class PlainView:
    """Plain lines on stderr (for logs and pipes): the step and its rule when it starts, a progress line every
    :data:`PLAIN_EVERY_S` seconds, each new problem once, and how the step ended."""

    def __init__(self, stream=None):
        self.stream = stream
        self._last = -float("inf")
        self._problems: set[str] = set()

    def _echo(self, text: str) -> None:
        click.echo(text, err=self.stream is None, file=self.stream)

    def on_step_start(self, step: str, words: str) -> None:
        self._echo(f"== {step}: {words}")
        self._problems = set()

    def __call__(self, status: StepStatus) -> None:
        now = time.monotonic()
        if self._last == -float("inf"):
            self._echo(f"rule: {status.rule}")
        for problem in status.problems:
            key = problem.split(" for ")[0]  # "sensor 3 stale for 1.2 s" once, not every time it grows
            if key not in self._problems:
                self._problems.add(key)
                self._echo(f"problem: {problem}")
        if now - self._last >= PLAIN_EVERY_S:
            self._last = now
            sensors = " ".join(f"{s.name}:{s.state}" for s in status.sensors)
            self._echo(f"{status.step}: {status.frames:,} frames, {status.elapsed_s:.1f} s; {_progress_words(status)}"
                       + (f"; thin: {status.thin}" if status.thin else "") + (f" [{sensors}]" if sensors else ""))

    def on_step(self, step, report: StepReport) -> None:
        self._echo(report.message)
        self._last = -float("inf")

    def close(self) -> None:
        pass


class RichView:
    """A live rich panel: the step's instruction and rule, a table of sensors (state, rate, jitter), a bar per
    target of the stop rule, the region still thin and the problems."""

    def __init__(self, console=None):
        from rich.console import Console
        from rich.live import Live

        self.console = console or Console(stderr=True)
        self.live = Live(console=self.console, refresh_per_second=4, transient=False)
        self.live.start()
        self._step_words = ""

    def on_step_start(self, step: str, words: str) -> None:
        self.console.print(f"[bold]{step}[/bold]: {words}")

    def __call__(self, status: StepStatus) -> None:
        from rich.console import Group
        from rich.table import Table
        from rich.text import Text

        sensors = Table(title=f"{status.step}: {status.frames:,} frames, {status.elapsed_s:.1f} s of tracker time",
                        title_justify="left")
        for column in ("sensor", "state", "rate (Hz)", "jitter (ms)"):
            sensors.add_column(column, justify="right" if "(" in column else "left")
        colours = {"OK": "green", "missing": "red", "stale": "yellow"}
        for k, s in enumerate(status.sensors):
            sensors.add_row(f"{k} {s.name}" if s.name != str(k) else str(k), f"[{colours[s.state]}]{s.state}[/]",
                            f"{s.rate_hz:.1f}", f"{s.jitter_ms:.2f}")
        bars = Table.grid(padding=(0, 1))
        for p in status.progress:
            colour = "green" if p.done else "cyan"
            bars.add_row(p.label, f"[{colour}]{_bar(p.fraction, 30)}[/]", f"{p.value:,.4g} / {p.target:,.4g} {p.unit}")
        parts = [Text(status.rule, style="dim"), sensors, bars]
        if status.thin:
            parts.append(Text(f"still thin: {status.thin}", style="yellow"))
        if status.done:
            parts.append(Text("done: the stop rule is met", style="bold green"))
        for problem in status.problems:
            parts.append(Text(f"problem: {problem}", style="red"))
        self.live.update(Group(*parts))

    def on_step(self, step, report: StepReport) -> None:
        style = {"done": "green", "kept": "yellow", "dropped": "red"}[report.outcome]
        self.console.print(f"[{style}]{report.message}[/]")

    def close(self) -> None:
        self.live.stop()


def make_view(rich: bool | None = None):
    """A :class:`RichView` when stderr is a terminal (or ``rich`` is True), else a :class:`PlainView`."""
    if rich is None:
        rich = sys.stderr.isatty()
    return RichView() if rich else PlainView()
