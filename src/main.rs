//! `r2d2`: the command-line front end. Each command lives in `cli/` and only turns options
//! into library calls.

mod cli;

/// Large blocks on transparent huge pages (see the type).
#[global_allocator]
static ALLOCATOR: r2d2_imaging::allocator::LargeBlocksOnHugePages = r2d2_imaging::allocator::LargeBlocksOnHugePages;

fn main() -> std::process::ExitCode {
    cli::main()
}
