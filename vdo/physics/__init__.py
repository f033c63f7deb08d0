"""What a camera sees of a point and what that is worth: visibility, lighting, the usable-view
weight, the predicted displacement and strain uncertainty and the design checks. The
differentiable objective is `vdo.objective`."""
