//! Where the command line looks for native ONNX Runtime before handing it to the engine
//! (`EngineOptions::onnx_runtime`): a policy of this machine's layout, kept out of the library.

use std::path::PathBuf;

/// Where native ONNX Runtime is looked for: `ORT_DYLIB_PATH`, then the `onnxruntime` Python
/// package (`onnxruntime/capi/libonnxruntime.so.*`) in the usual site-packages places, then
/// the one `python3` imports.
pub fn find_onnxruntime() -> std::result::Result<PathBuf, String> {
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH").filter(|p| !p.is_empty()) {
        let p = PathBuf::from(p);
        return if p.is_file() { Ok(p) } else { Err(format!("ORT_DYLIB_PATH={} is not a file", p.display())) };
    }
    let mut roots: Vec<String> = Vec::new();
    if let Some(venv) = std::env::var_os("VIRTUAL_ENV") {
        roots.push(format!("{}/lib/python3*/site-packages", venv.to_string_lossy()));
    }
    if let Some(home) = std::env::var_os("HOME") {
        let home = home.to_string_lossy();
        roots.push(format!("{home}/.local/lib/python3*/site-packages"));
        roots.push(format!("{home}/.pyenv/versions/*/lib/python3*/site-packages"));
    }
    roots.extend(["/usr/local/lib/python3*/site-packages", "/usr/local/lib/python3*/dist-packages", "/usr/lib/python3/dist-packages"].map(String::from));
    for root in &roots {
        if let Some(lib) = glob_library(&format!("{root}/onnxruntime/capi/libonnxruntime.so*")) {
            return Ok(lib);
        }
    }
    // Last resort: ask the Python on PATH where its onnxruntime lives.
    let out = std::process::Command::new("python3")
        .args(["-c", "import onnxruntime, os; print(os.path.dirname(onnxruntime.__file__))"])
        .stderr(std::process::Stdio::null())
        .output();
    if let Ok(out) = out {
        if out.status.success() {
            let dir = String::from_utf8_lossy(&out.stdout).trim().to_string();
            if let Some(lib) = glob_library(&format!("{dir}/capi/libonnxruntime.so*")) {
                return Ok(lib);
            }
        }
    }
    Err("no ORT_DYLIB_PATH and no onnxruntime Python package found (pip install onnxruntime, or set ORT_DYLIB_PATH)".into())
}

fn glob_library(pattern: &str) -> Option<PathBuf> {
    let mut found: Vec<PathBuf> = glob::glob(pattern).ok()?.filter_map(|p| p.ok()).filter(|p| p.is_file()).collect();
    found.sort();
    found.pop()
}
