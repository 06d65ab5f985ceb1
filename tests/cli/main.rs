//! Integration tests of the `pipe` library and CLI (one test binary, one module per area).

mod deformed_render;
mod deps;
mod edit;
mod formats;
mod ingest;
mod init;
mod physdreamer;
mod physics;
mod render;
mod resume;
mod runner;
mod simulate;
mod spec_errors;
mod support;
mod tables;
mod two_material;
mod warmup;
