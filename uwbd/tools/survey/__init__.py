"""``uwbd survey``: the anchor positions, from the ranges in a log.

Tape-measured anchors are off by 5-20 cm; that error reaches every fix. Two kinds of range
fix the anchors' layout:

* **anchor-to-anchor ranges** (TREK1000 ``ma`` reports, :class:`~drivers.frames.AnchorRanges`
  on ``/anchor_ranges`` or decoded from the raw bytes): each pair's repeated ranges are
  reduced to their median (an NLOS range or a glitch does not move it) and the standard
  error of that median (1.2533 x 1.4826 MAD / √n, at least 2 mm). Classical
  multilateration places the anchors from the horizontal distances alone, one after
  another (the best-connected pair on an axis, then each anchor by two-circle
  intersection, the side chosen by a third placed neighbour, and Gauss-Newton against all
  of them), independently of the configured positions; the layout is then carried into the
  output frame and one least-squares adjustment takes every pair at once (least squares:
  the medians are robust already). The TREK1000 reports A0-A1, A0-A2 and A1-A2 only: 3
  ranges fix the triangle A0 A1 A2 (its 3 side lengths) exactly, with nothing left over to
  check them; they fix nothing about A3 (kept as configured), the heights, where the
  triangle sits and points (the gauge, below) or its mirror image, and an antenna-delay
  error scales the triangle whatever the averaging.
* **a moving tag's ranges** (``UwbRanges``): one batch nonlinear least squares
  (:func:`scipy.optimize.least_squares`, trust region with LSMR, an analytic sparse
  Jacobian) over the tag's path and the anchors together: one tag position per UWB epoch
  with 4 ranges or more (an epoch with 3 says nothing about the anchors), or, for one
  asynchronous range per message, a position every 0.2 s with the tag moving linearly
  between them; optionally (``range_offsets``) a range offset per anchor (its antenna
  delay), tied to 0 with ``[fusion] range_bias_sigma_m``. It starts from the configured
  anchors, and takes the log's anchor-to-anchor ranges too. The loss on the tag's ranges is
  ``arctan`` at 2 σ (redescending: a range 6 σ off weighs 1/80 of a good one), since NLOS
  comes in bursts that bias ranges for seconds and ``soft_l1`` or Huber still let them pull
  the layout by decimetres; the tag's path is first solved alone (anchors held) with the
  same loss, so that the joint solve starts with the NLOS ranges already recognised. A
  safeguard, measured necessary (``benchmarks/bench_survey.py``): a tag position per
  epoch from few ranges biases the anchors along the directions the ranges fix poorly (a
  Neyman-Scott effect: thousands of nuisance positions), and ceiling anchors over a ground
  robot have such directions (the layout's scale against the tag's height, a twist of the
  heights). So the ranges' own information about the anchors is computed at the start (the
  tag positions and offsets marginalised, the priors' information taken out) and the anchors
  move only along its eigen-directions that the ranges fix at least twice as well (in σ) as
  the priors; the rest stays as configured, and says so.

Where the config has ``[range_model] log_distance_m`` (a DW1000's range grows
``k ln(d / 1 m)`` beyond the distance), that term comes off every range first, the tag's and
the anchors' alike; left in, it stretches the layout. On a simulated handheld run with
``0.15 ln(d / 1 m)`` in its ranges: the layout 0.29 m RMS off with it left in, 0.061 m with
it taken off, 0.064 m from clean ranges.

**Heights** are held at the config's (or ``--height``) when the anchors lie on one plane
within 0.3 m RMS, as ceiling anchors do: a range's change with a height difference dz is
dz/r, nothing at dz = 0, so ranges within the plane do not see heights, and a tag on one
side of it sees them hardly (what it sees, a twist of the heights, the NLOS bias pushes:
measured worse than the tape). Otherwise they are estimated (tied to the configured ones
like every coordinate, below). Heights are what a laser or a tape held vertically measures
well: ``--height`` for each anchor is the way to get them right.

**The gauge.** Ranges fix the layout only up to a rigid motion (3 translations, 3
rotations) and a mirror image. Two ways to fix it, both offered:

* by default every configured coordinate is a measurement of that anchor, σ
  ``prior_sigma_m`` (0.2 m): this ties the layout softly to where it was tape-measured,
  keeps the config's frame (the frame the robot's map is in) and adds what the tape
  measure knows about the shape. Where the layout as a whole sits is then known only to
  about σ/√n (the tape measure's average error), and that part of the tape error stays in
  the result: ranges cannot see it.
* ``--origin O --x-axis X [--y-side Y]``: the user's frame: O at (0, 0), X on the +x axis
  (its y = 0), Y on the +y side (by default the side the config puts it on); these hold
  exactly, and the priors, carried into that frame, fix the rest (the vertical and the
  tilt, softly: the heights' average). The config is carried into that frame first
  (translated and turned so O and X are where the frame puts them).

A ``--height`` holds that anchor's height exactly. A frame is right-handed with z up: a
``--y-side`` anchor that the config puts on the -y side is refused (it would mirror the
frame).

**Uncertainty**: the covariance σ0² (JᵀJ)⁻¹ at the solution (J with the robust loss's
weights; the tag positions eliminated by the Schur complement), σ0 the residuals' robust
scale (1.4826 MAD, in units of the range σ) for tag ranges, 1 for anchor-to-anchor ranges
(whose σ is their own scatter); the directions left as configured keep the priors' σ; 1-σ
per axis. It holds the range noise only: an NLOS detour held for seconds or an antenna
delay is not in it. In the default gauge it includes where the frame sits;
``layout_sigma_m`` is the part that is the anchors relative to each other (the covariance
with the rigid motions projected out).

Needs scipy (the ``tools`` extra).
"""

from uwbd.tools.survey.estimate import log_ranges, survey, without_distance_term
from uwbd.tools.survey.model import (
    AnchorEstimate,
    Gauge,
    PairRange,
    Settings,
    Survey,
    SurveyError,
)
from uwbd.tools.survey.output import anchors_document, orientations_of, table, with_anchors

__all__ = ["AnchorEstimate", "Gauge", "PairRange", "Settings", "Survey", "SurveyError",
           "anchors_document", "log_ranges", "orientations_of", "survey", "table",
           "with_anchors",
           "without_distance_term"]
