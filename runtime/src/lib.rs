//! The Kiln runtime (under construction).
