//! The `pipe` command.

fn main() -> std::process::ExitCode {
    pipe::cli::main(std::env::args_os(), pipe::stages::builtin())
}
