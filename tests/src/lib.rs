//! Helpers for the farm's integration tests.
