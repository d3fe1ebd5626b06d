//! Records the exact tract version resolved in Cargo.lock, so `r2d2 info` reports the backend
//! actually compiled in (no tract API gives it at run time).

fn main() {
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
