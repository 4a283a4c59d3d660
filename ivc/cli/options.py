"""Option types shared by the commands: ranges checked by click, so a bad value is a one-line usage error."""

from __future__ import annotations

import math

import click


class PositiveFloat(click.ParamType):
    """A finite number above zero (click's FloatRange lets NaN through)."""

    name = "number > 0"

    def convert(self, value, param, ctx):
        if isinstance(value, float) and math.isfinite(value) and value > 0:
            return value
        try:
            number = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number", param, ctx)
        if not (math.isfinite(number) and number > 0):
            self.fail(f"{value!r} must be a finite number above 0", param, ctx)
        return number


POSITIVE = PositiveFloat()


class RateHz(PositiveFloat):
    """A sample rate (Hz) inside :data:`ivc.app.inputs.RATE_RANGE_HZ`, refused before any work."""

    name = "Hz"

    def convert(self, value, param, ctx):
        from ivc.app.inputs import RATE_RANGE_HZ

        rate = super().convert(value, param, ctx)
        low, high = RATE_RANGE_HZ
        if not low <= rate <= high:
            self.fail(f"{rate:g} Hz is outside the sample rates of a tracker stream, {low:g} to {high:g} Hz", param,
                      ctx)
        return rate


RATE_HZ = RateHz()
#: a seed NumPy takes (non-negative) and a session stores (a 64-bit signed attribute: ivc.sim.protocol.MAX_SEED)
SEED = click.IntRange(0, 2**63 - 1)
#: most frames one simulated step may have: 20 times the protocol's 100,000-frame sweep (memory grows with it)
MAX_SIM_FRAMES = 2_000_000
SIM_FRAMES = click.IntRange(1, MAX_SIM_FRAMES)


class HiddenAliases(click.Option):
    """An option whose first name is shown in ``--help`` and whose other names still work, unlisted (an old
    flag kept for scripts: ``--tracker`` for ``--solver``)."""

    def get_help_record(self, ctx):
        names = self.opts
        self.opts = names[:1]
        try:
            return super().get_help_record(ctx)
        finally:
            self.opts = names


def solver_option(help: str, dest: str = "solver", **kwargs):
    """``--solver closed-form|least-squares``: the tracker's own pose solver (``--tracker``, its old name, still
    works)."""
    from ivc.pose.tracker_solver import SOLVERS

    return click.option("--solver", "--tracker", dest, cls=HiddenAliases, type=click.Choice(SOLVERS), help=help,
                        **kwargs)
