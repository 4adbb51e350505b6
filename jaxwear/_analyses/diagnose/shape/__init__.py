"""The shape of the missing wear (design.md §7, `diagnose --shape`), one module a step:

- `linear`: the shape's columns along each state variable, whitened, and the linearised
  system every later step reads (the law search's screen included);
- `analysis`: the analysis itself, from the base fit to a `result.ShapeResult`: tests per
  variable with a simulated null, the form (factor or deposit), the best variable;
- `choice`: which of tied variables is kept (unique share, left-out error), `interaction`:
  the product surface over the leading pair;
- `refit`: the chosen correction refitted through the wear loop by the one least-squares
  core; `map`: when and where on the joint the missing wear is made;
- `design`: the state variables' columns and the load history they come from;
- `result`, `text`: what a user gets back, as data and as sentences.

The modules import one another directly (no names are re-exported here), so that importing
one step does not import the whole analysis.
"""
