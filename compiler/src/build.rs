//! The orchestration shared by `kiln build` and the build-script API (under construction).
