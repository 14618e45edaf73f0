"""Statistics of shape changes: correlation functions and the Roman additive shear budget."""
