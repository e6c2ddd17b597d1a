"""Global choice of the way round every obstacle: the exact shortest route among the ellipses.

The outside constraint ‖A z + b‖ ≥ 1 is not convex, so a local method started from the straight line
settles on whichever side of an obstacle it happens to start on, and a U-shaped group of obstacles
traps it. Among convex obstacles a shortest path is made of segments tangent to the obstacles (or
ending at a terminal: the start or a goal) and arcs along their boundaries: the tangent graph (Liu &
Arimoto 1992; Latombe, Robot Motion Planning, ch. 4). It is built here exactly, on the ellipses
themselves scaled to the planning level ‖A z + b‖ = level (so the refinement starts on its own
feasible set), rather than on polygons round them: a polygon's corners close marginal passages and
move tangent points, and no polygon size is right for every map.

The search, one module per question: `frames` (each ellipse as the unit circle), `roots` (real roots
of degree-2 trigonometric polynomials), `tangents` (the candidate segments), `arcs` (free and blocked
stretches of each boundary), `cells` (a cheap proof a segment is blocked), `graph` (the tangent graph
and Dijkstra on it).

* Common tangents of ellipses i and j. In i's unit-disc frame the tangent line at angle θ,
  {x : nᵀx = 1} with n = (cos θ, sin θ), touches j (centre c, shape S there) exactly when
  nᵀc ± √(nᵀSn) = 1 (j's support function: + an outer tangent, both on one side; − an inner one).
  Squared, F(θ) = (1 − nᵀc)² − nᵀSn is a trigonometric polynomial of degree 2, a quartic in e^{iθ}:
  at most four tangents. When j's bounding disc is clear of the unit circle (|c| > 1 + ρ, ρ² the
  largest eigenvalue of S) there are exactly four, one of each sign in each of the windows
  |θ − ∠c| ∈ [acos((1 + ρ)/|c|), acos((1 − ρ)/|c|)], where the sign is known at both ends: found by
  safeguarded Newton — only where the window meets a free arc of i, and the window of j where that
  tangent touches j (the same construction from j's side) a free arc of j: the graph drops the rest.
  Close pairs (few: neighbours) bracket F's roots on a grid (`roots.trig_roots`).
* Tangents from a terminal: at angles ∠q ± acos(1/|q|) for q the terminal in the unit-disc frame.
* Arcs. Each ellipse's boundary is cut where another ellipse crosses it (‖M u(θ) + d‖² = 1, again a
  degree-2 trigonometric polynomial) or a map bound does (a cosine); between consecutive cuts an arc
  is wholly free or wholly blocked (how many obstacles cover it is counted round the boundary).
  Consecutive tangent points on a free arc are joined by it, at its exact length (Gauss–Legendre on
  the speed ‖A⁻¹ u′(θ)‖).

Tangent points inside another ellipse are dropped; every remaining tangent segment is checked exactly
against the other ellipses whose bounding disc it reaches (eq. 2 on the continuous segment; the pairs
from `EllipseStack.segment_pairs_swept`). In a dense field nearly all of them are
blocked, most through the depth of some ellipse: a point sampled on the segment in a grid cell wholly
inside an ellipse proves that at a fraction of the exact test's cost (`cells.DeepCells`, built once enough
segments wait for a test to pay for the grid), so only the rest get the exact one. Dijkstra then picks
every side globally. Only points x with ‖x − from‖ + ‖x − to‖ ≤ bound can lie on a leg no longer than
`bound`, so the graph is built within that informed ellipse, starting a little above the straight
distance and widening it (to the length of a route found beyond the bound, else by a factor) until the
leg found is within it — then it is the exact shortest. Tangents, cuts and segment tests are kept as it
widens.
"""

from services.planner.route.graph import KeepTo, Route, shortest_route, tangent_route

__all__ = ["KeepTo", "Route", "shortest_route", "tangent_route"]
