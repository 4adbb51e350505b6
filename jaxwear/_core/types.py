"""Shape/dtype aliases used in annotations (jaxtyping style, documentation only)."""

from jaxtyping import Array, Bool, Float, Int

Scalar = Float[Array, ""]
NodeArray = Float[Array, " nodes"]
StepArray = Float[Array, " steps"]
StepNodeArray = Float[Array, "steps nodes"]
Vec2 = Float[Array, "... 2"]

__all__ = ["Array", "Bool", "Float", "Int", "Scalar", "NodeArray", "StepArray", "StepNodeArray",
           "Vec2"]
