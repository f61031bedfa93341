"""Sub-cell registration: `register` against the quadratic peak fit and SimpleITK on real photographs."""
