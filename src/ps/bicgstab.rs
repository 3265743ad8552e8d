//! Block BiCGStab (placeholder, filled in by the solver change).
