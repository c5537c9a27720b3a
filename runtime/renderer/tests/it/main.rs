//! The bundled renderer's integration tests, one binary: `kiln-view` as a child process,
//! hostile archives, pipelines created as frames ask for them, and the scan for module
//! cycles (`kiln_view_watch` with `hot-reload`).

mod hostile_archives;
mod kiln_view;
#[cfg(feature = "hot-reload")]
mod kiln_view_watch;
mod lazy_pipelines;
mod module_cycles;
mod setup_errors;
