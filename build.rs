//! Records the exact tract version resolved in Cargo.lock, so `r2d2 info` reports the backend
//! actually compiled in (no tract API gives it at run time), and lists the telescopes' antenna
//! tables (`data/telescopes/*.itrf.txt`) for `src/simulate/telescope.rs` to compile in: a new
//! telescope is its data files only.

use std::path::Path;

fn main() {
    antenna_tables();
    println!("cargo:rerun-if-changed=Cargo.lock");
    let lock = std::fs::read_to_string("Cargo.lock").unwrap_or_default();
    let version = lock
        .split("[[package]]")
        .find(|block| block.contains("name = \"tract-onnx\""))
        .and_then(|block| block.lines().find_map(|l| l.strip_prefix("version = \"")))
        .map(|v| v.trim_end_matches('"').to_string())
        .unwrap_or_else(|| "0.23 (exact version unknown: no Cargo.lock)".to_string());
    println!("cargo:rustc-env=R2D2_TRACT_VERSION={version}");
}

/// Writes `$OUT_DIR/antenna_tables.rs`: every antenna table of `data/telescopes`, by file name,
/// as `(name, include_str!(its path))`, in name order.
fn antenna_tables() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/telescopes");
    println!("cargo:rerun-if-changed=data/telescopes");
    let mut tables: Vec<(String, std::path::PathBuf)> = std::fs::read_dir(&dir)
        .expect("data/telescopes")
        .map(|entry| entry.expect("data/telescopes entry").path())
        .filter_map(|path| Some((path.file_name()?.to_str()?.to_string(), path.clone())))
        .filter(|(name, _)| name.ends_with(".itrf.txt"))
        .collect();
    tables.sort();
    let entries: Vec<String> = tables.iter().map(|(name, path)| format!("    ({name:?}, include_str!({:?})),\n", path.display().to_string())).collect();
    let out = Path::new(&std::env::var("OUT_DIR").expect("OUT_DIR")).join("antenna_tables.rs");
    std::fs::write(out, format!("&[\n{}]\n", entries.concat())).expect("write antenna_tables.rs");
}
