//! Integration tests of the `pipe` library and CLI (one test binary, one module per area).

mod formats;
mod ingest;
mod init;
mod render;
mod runner;
mod simulate;
mod spec_errors;
mod support;
mod tables;
mod warmup;
