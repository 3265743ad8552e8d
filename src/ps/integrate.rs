//! Perspective normal integration (placeholder, filled in by the integration change).
