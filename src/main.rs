//! `r2d2`: the command-line front end; the commands live in the library's `cli` module.

/// Large blocks on transparent huge pages (see the type).
#[global_allocator]
static ALLOCATOR: r2d2_imaging::LargeBlocksOnHugePages = r2d2_imaging::LargeBlocksOnHugePages;

fn main() -> std::process::ExitCode {
    r2d2_imaging::cli::main()
}
