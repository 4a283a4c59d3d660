"""Plain-word checks of a recorded step, run while collecting (Himberg 2010, ch. 4.4.3).

They warn and do not refuse: a user may know better (a short test capture, say), and
``ivc fit`` refuses later what it cannot use.
"""

from __future__ import annotations

import numpy as np

from ivc import rotations
from ivc.session import STEPS, Session, Step, is_extension_step, step_order

#: Himberg 2010's minimum frame counts
MIN_FRAMES = {"cube_calibration": 1000}
DEFAULT_MIN_FRAMES = 100
STATIC_STEPS = ("cube_calibration", "cube_survey", "wand_calibration")
#: a static fixture whose sensors move more than this was not static (well above tracker jitter)
STATIC_POSITION_SPREAD = 0.002  # m, 99th minus 1st percentile
STATIC_ANGLE_SPREAD = 0.02  # rad
INVALID_FRACTION_WARNING = 0.01


#: sample rates outside this range (Hz) are warned about: a time column in another unit
MIN_PLAUSIBLE_RATE_HZ, MAX_PLAUSIBLE_RATE_HZ = 1.0, 100_000.0


def rate_warning(step: Step) -> str | None:
    """Plain words when a recording's sample rate is implausible for a tracker (times in ms under ``time``?)."""
    rate = step.sample_rate_hz
    if rate < MIN_PLAUSIBLE_RATE_HZ:
        return (f"the sample rate inferred from the times is {rate:.3g} Hz: trackers sample at 10-1000 Hz. If the "
                "times are in milliseconds, name the column time_ms (or pass sample_rate_hz=HZ)")
    if rate > MAX_PLAUSIBLE_RATE_HZ:
        return (f"the sample rate inferred from the times is {rate:.3g} Hz: trackers sample at 10-1000 Hz. Are the "
                "times in seconds?")
    return None


def check_step(name: str, step: Step, session: Session | None = None, hemisphere: str = "+x") -> list[str]:
    """Warnings, in plain words, about a step about to be added to ``session``."""
    warnings = []
    rate = rate_warning(step)
    if rate:
        warnings.append(f"{name}: {rate}")
    minimum = MIN_FRAMES.get(name, DEFAULT_MIN_FRAMES)
    if name != "check" and step.n_frames < minimum:
        warnings.append(f"{name} has {step.n_frames} frames; the method wants at least {minimum}")
    valid = step.valid_mask
    for k, sensor in enumerate(step.names):
        bad = 1.0 - valid[:, k].mean()
        if bad > INVALID_FRACTION_WARNING:
            warnings.append(f"sensor {sensor} was dropped or saturated in {100 * bad:.1f}% of {name}'s frames")
    if name in STATIC_STEPS:
        position, quaternion = step.poses(hemisphere)
        for k, sensor in enumerate(step.names):
            ok = valid[:, k]
            if ok.sum() < 2:
                continue
            p = position[ok, k]
            spread = np.max(np.percentile(p, 99, axis=0) - np.percentile(p, 1, axis=0))
            angles = rotations.angle_between(quaternion[ok, k], rotations.mean(quaternion[ok, k]))
            if spread > STATIC_POSITION_SPREAD or np.percentile(angles, 99) > STATIC_ANGLE_SPREAD:
                warnings.append(
                    f"the fixture was not static during {name}: sensor {sensor} moved {1000 * spread:.1f} mm "
                    f"and {1000 * np.percentile(angles, 99):.0f} mrad; record it again with the fixture still"
                )
                break
    if session is not None and is_extension_step(name):
        reach = reach_warning(name, step, session, hemisphere)
        if reach:
            warnings.append(reach)
    if session is not None:
        earlier = [s for s in STEPS if step_order(s) < step_order(name) and s != "check" and s not in session.steps]
        if earlier and name != "check":
            warnings.append(f"{name} recorded before {', '.join(earlier)}: the protocol's order is {', '.join(STEPS)}")
    return warnings


#: an extension sweep is warned about when no sensor was reported within the wand's reach of the
#: declared cube position plus this slack (the reported poses are distorted by centimetres)
REACH_SLACK = 0.05


def reach_warning(name: str, step: Step, session: Session, hemisphere: str = "+x") -> str | None:
    """Plain words when extension sweep ``name`` never came near the region the cube sweep maps: no sensor's
    reported position within the wand's length plus the cube's size (and :data:`REACH_SLACK`) of the declared
    cube position. Such a sweep cannot be solved (``ivc fit`` also reports it); None when it did, or when the
    session lacks the cube survey or the wand calibration to tell."""
    survey, calibration = session.steps.get("cube_survey"), session.steps.get("wand_calibration")
    if survey is None or calibration is None or "declared_position" not in survey.attrs:
        return None
    wand_position, _ = calibration.poses(hemisphere)
    length = float(np.nanmax(np.linalg.norm(np.nanmean(wand_position, axis=0) - np.nanmean(wand_position[:, 0],
                                                                                           axis=0), axis=-1)))
    cube_position, _ = survey.poses(hemisphere)
    centre = np.nanmean(cube_position.reshape(-1, 3), axis=0)
    cube_size = float(np.nanmax(np.linalg.norm(np.nanmean(cube_position, axis=0) - centre, axis=-1)))
    position, _ = step.poses(hemisphere)
    distance = np.linalg.norm(position - centre, axis=-1)[step.valid_mask]
    distance = distance[np.isfinite(distance)]
    if len(distance) == 0:
        return None
    reach = length + cube_size + REACH_SLACK
    if distance.min() > reach:
        return (f"{name} never came near the region mapped from the cube: its sensors stayed at least "
                f"{1000 * distance.min():.0f} mm from the cube (the wand reaches {1000 * reach:.0f} mm); an "
                "extension sweep needs part of the wand inside the mapped region: record it again, starting with "
                "the wand's tip at the cube")
    return None
