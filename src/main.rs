//! `r2d2`: the command-line front end. Each command lives in `cli/` and only turns options
//! into library calls.

mod cli;

fn main() -> std::process::ExitCode {
    cli::main()
}
