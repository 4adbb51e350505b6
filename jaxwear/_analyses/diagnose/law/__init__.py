"""From the shape to a law (design.md §7 `shape.law`): the search as one pipeline.

1. **Screen** (`screen`): every one- and two-term law of the grammar on the shape's
   linearised system, no model run; the best of distinct structure go on.
2. **Fit** (`search`, starts by forward runs in `start`): each through the wear loop by the
   one least-squares core, on one compiled model; then, where the history shows, laws with
   memory (`memory`).
3. **Guard** (`search.unbounded`, `search.bounded`, `search.undetermined`): a law unbounded
   where a prediction goes is refused where no cap bounds it (a negative power of a state
   that reaches zero), an exponential that grows too much beyond the states met is held
   flat above them (said), constants the data do not determine are named.
4. **Rank** (`search.rank`): the simplest law within one standard error of the best
   left-out error, a lead after a determined law the evidence far prefers
   (`search.outranked`); found only where it predicts (`result.LawResult.status`).

`result` holds what the search returns and its sentence. The modules import one another
directly (no names are re-exported here).
"""
