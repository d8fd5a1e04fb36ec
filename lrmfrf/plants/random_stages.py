"""Random wafer-stage-like plants, to test promises on stages nobody tuned on.

:func:`random_stage` draws a stage of the same kind as
:func:`lrmfrf.plants.wafer_stage` (SISO: a rigid body, flexible modes, a
collocated feedback output ``y4`` and a non-collocated output ``z``, a lead-PID
loop) or :func:`lrmfrf.plants.mimo_wafer_stage` (``mimo=True``: the four-corner
plate with random plate modes and geometry). What is drawn:

* 2-6 flexible modes between 80 Hz and 0.95 x the fast Nyquist frequency,
  damping 0.3-3 % (log-uniform);
* about half of the modes after the first are placed so that they alias, for the
  stage's ``F`` (2-5), onto or next to an earlier mode: at ``j f_s,slow +- f_b (1 +
  d)`` with ``|d| <= 3 %`` (:attr:`RandomDraw.aliasing_pairs` lists them);
* collocated participations (``y4``, or the plate's corner patterns) positive,
  0.02-0.4; non-collocated ones (``z``, the point of interest) of random sign,
  0.1-1.5;
* the mass (1-20 kg, log-uniform) and a lead-PID bandwidth of 20-80 Hz;
* for ``loop="open"`` (SISO) a suspension of the body, 2-10 Hz with 5-20 %
  damping, from a child generator (so the rest of the draw equals the
  closed-loop stage of the same seed): a free body has no periodic steady
  state and drifts away in an open-loop experiment.

A draw whose closed loop is unstable or has less than ``min_phase_margin``
degrees of phase margin (or 2 of gain margin) is redrawn; every returned loop
has been checked. The same ``rng`` seed gives the same stage.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .._validation import check_rng, check_sample_time
from .mimo_stage import PlateMode, mimo_wafer_stage
from .siso_stage import Mode, _check_suspension, _named, wafer_stage

__all__ = ["RandomDraw", "random_stage"]

#: Corner patterns of the plate modes (corners 1-4): heave, roll, pitch, torsion.
PLATE_PATTERNS = {
    "heave": (1.0, 1.0, 1.0, 1.0),
    "roll": (1.0, 1.0, -1.0, -1.0),
    "pitch": (-1.0, 1.0, 1.0, -1.0),
    "torsion": (1.0, -1.0, 1.0, -1.0),
}


@dataclass(frozen=True)
class RandomDraw:
    """What :func:`random_stage` drew, next to the stage it returns.

    Attributes
    ----------
    downsampling_factor : int
        ``F`` the modes were placed for.
    frequencies_hz : tuple of float
        Flexible-mode frequencies in Hz, in plant order.
    aliasing_pairs : tuple of (int, int)
        ``(i, j)``: mode ``i`` was placed to alias onto or next to mode ``j``.
    tries : int
        Draws needed for a loop that met the margins.
    """

    downsampling_factor: int
    frequencies_hz: tuple[float, ...]
    aliasing_pairs: tuple[tuple[int, int], ...]
    tries: int


def random_stage(
    rng=None,
    *,
    n_modes: int | None = None,
    loop: str = "closed",
    mimo: bool = False,
    downsampling_factor: int | None = None,
    sample_time: float = 0.5e-3,
    min_phase_margin: float = 30.0,
    max_tries: int = 200,
    suspension=None,
):
    """Draw a random wafer-stage-like plant with a checked feedback loop.

    Parameters
    ----------
    rng : None, int or numpy.random.Generator
        Seed or generator (the same seed gives the same stage).
    n_modes : int, optional
        Number of flexible modes, 1-12; default drawn from 2-6.
    loop : {"closed", "open"}, default "closed"
        SISO only: ``"closed"`` gives the equivalent closed-loop systems as
        ``G_y4``/``G_z`` (as :func:`wafer_stage`), ``"open"`` the plant's own
        channels (the controller is still designed, checked and returned).
    mimo : bool, default False
        Draw the four-corner plate (:class:`MIMOWaferStage`) instead.
    downsampling_factor : int, optional
        ``F`` the aliasing placement is for; default drawn from 2-5.
    sample_time : float, default 0.5e-3
        Fast sample time in s.
    min_phase_margin : float, default 30.0
        Smallest phase margin in degrees of every returned loop.
    max_tries : int, default 200
        Draws before giving up.
    suspension : bool, (frequency_hz, damping) or None
        SISO only. ``True``: suspend the body on a drawn spring and damper
        (2-10 Hz, damping 5-20 %, log-uniform), a stable plant; ``False``: a
        free rigid body; a pair: that suspension. Default (``None``):
        suspended for ``loop="open"`` (a free body drifts away in an open-loop
        experiment and has no periodic steady state), free for
        ``loop="closed"``.

    Returns
    -------
    stage : WaferStage or MIMOWaferStage
    draw : RandomDraw

    Raises
    ------
    RuntimeError
        If no draw met the margins in ``max_tries``.

    Examples
    --------
    >>> stage, draw = random_stage(0)
    >>> 2 <= draw.downsampling_factor <= 5 and stage.margins().phase_margin >= 30
    True
    """
    generator = check_rng(rng)
    sample_time = check_sample_time(sample_time)
    if loop not in ("closed", "open"):
        raise ValueError(f"`loop` must be 'closed' or 'open'; got {loop!r}.")
    if loop == "open" and mimo:
        raise ValueError("loop='open' is for SISO stages; pass mimo=False.")
    if suspension is None:
        suspension = loop == "open" and not mimo
    if mimo and suspension is not False:
        raise ValueError("`suspension` is for SISO stages; pass mimo=False.")
    if suspension is not True and suspension is not False:
        suspension = _check_suspension(suspension)
    if suspension is True:
        # from a child generator: the rest of the draw is the same stream as
        # for a free body (spawning does not advance ``generator``)
        child = generator.spawn(1)[0]
        suspension = (
            float(np.exp(child.uniform(np.log(2.0), np.log(10.0)))),
            float(np.exp(child.uniform(np.log(0.05), np.log(0.2)))),
        )
    F = (
        int(generator.integers(2, 6))
        if downsampling_factor is None
        else int(downsampling_factor)
    )
    if not 1 <= F <= 20:
        raise ValueError(f"`downsampling_factor` must be in 1..20; got {F}.")
    count = int(generator.integers(2, 7)) if n_modes is None else int(n_modes)
    if not 1 <= count <= 12:
        raise ValueError(f"`n_modes` must be in 1..12; got {n_modes!r}.")
    for tries in range(1, max_tries + 1):
        frequencies, pairs = _mode_frequencies(generator, count, F, sample_time)
        damping = np.exp(generator.uniform(np.log(0.003), np.log(0.03), count))
        mass = float(np.exp(generator.uniform(np.log(1.0), np.log(20.0))))
        bandwidth = float(generator.uniform(20.0, 80.0))
        try:
            if mimo:
                stage = _plate(generator, frequencies, damping, mass, bandwidth, F,
                               sample_time)
                margins = list(stage.margins().values())
            else:
                stage = _siso(generator, frequencies, damping, mass, bandwidth, F,
                              sample_time, loop, suspension or None)
                margins = [stage.margins()]
        except ValueError:  # the loop is unstable: draw again
            continue
        if all(m.phase_margin >= min_phase_margin and m.gain_margin >= 2.0
               for m in margins):
            draw = RandomDraw(F, tuple(frequencies), tuple(pairs), tries)
            return stage, draw
    raise RuntimeError(
        f"no random stage met phase margin >= {min_phase_margin} deg in {max_tries} "
        "draws; lower min_phase_margin or raise max_tries."
    )


def _mode_frequencies(generator, count: int, F: int, sample_time: float):
    """Mode frequencies in Hz, about half placed to alias onto earlier modes."""
    low, high = 80.0, 0.95 / (2.0 * sample_time)
    slow_rate = 1.0 / (F * sample_time)
    frequencies: list[float] = []
    pairs: list[tuple[int, int]] = []
    while len(frequencies) < count:
        placed = None
        if frequencies and F > 1 and generator.random() < 0.5:
            base = int(generator.integers(len(frequencies)))
            offset = 1.0 + generator.uniform(-0.03, 0.03)
            options = [
                j * slow_rate + sign * frequencies[base] * offset
                for j in range(1, F + 1)
                for sign in (-1.0, 1.0)
            ]
            options = [f for f in options if low <= f <= high]
            if options:
                placed = float(options[int(generator.integers(len(options)))])
                pairs.append((len(frequencies), base))
        if placed is None:
            placed = float(np.exp(generator.uniform(np.log(low), np.log(high))))
        if all(abs(placed - f) > 0.02 * f for f in frequencies):
            frequencies.append(placed)
        elif pairs and pairs[-1][0] == len(frequencies):
            pairs.pop()
    return frequencies, pairs


def _siso(generator, frequencies, damping, mass, bandwidth, F, sample_time, loop,
          suspension):
    modes = [
        Mode(
            f,
            float(z),
            float(np.exp(generator.uniform(np.log(0.02), np.log(0.4)))),
            float(generator.choice([-1.0, 1.0])
                  * np.exp(generator.uniform(np.log(0.1), np.log(1.5)))),
        )
        for f, z in zip(frequencies, damping, strict=True)
    ]
    stage = wafer_stage(sample_time=sample_time, mass=mass, modes=modes,
                        controller_bandwidth=bandwidth, downsampling_factor=F,
                        suspension=suspension)
    if loop == "open":
        stage = replace(stage, G_y4=_named(stage.plant[0, 0], "P_y4", "y4"),
                        G_z=_named(stage.plant[1, 0], "P_z", "z"))
    return stage


def _plate(generator, frequencies, damping, mass, bandwidth, F, sample_time):
    names = list(PLATE_PATTERNS)
    modes = []
    for f, z in zip(frequencies, damping, strict=True):
        pattern = np.asarray(PLATE_PATTERNS[names[int(generator.integers(4))]])
        corner = float(np.exp(generator.uniform(np.log(0.14), np.log(0.63))))
        poi = float(generator.choice([-1.0, 1.0])
                    * np.exp(generator.uniform(np.log(0.1), np.log(1.5))) / corner)
        modes.append(PlateMode(f, float(z), tuple(corner * pattern), poi))
    half = tuple(generator.uniform(0.08, 0.2, 2))
    poi_xy = tuple(generator.uniform(-0.8, 0.8, 2) * np.asarray(half))
    return mimo_wafer_stage(sample_time=sample_time, mass=mass, modes=modes,
                            controller_bandwidth=bandwidth, downsampling_factor=F,
                            half_width=half, poi=poi_xy)

