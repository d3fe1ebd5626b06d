//! `r2d2 models`: the model series found under a directory (default `models/`), by the
//! telescope they were trained for, with their manifests' key facts.

use crate::steps::series::{discover, model_dirs, Architecture};
use crate::Result;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Directory holding one sub-directory per series (default: the first model directory
    /// that exists: $R2D2_MODELS, ./models, the repository's or the installation's models/).
    dir: Option<PathBuf>,
}

pub fn run(args: Args) -> Result<()> {
    let dir = args.dir.unwrap_or_else(|| {
        let dirs = model_dirs();
        dirs.iter().find(|d| d.is_dir()).cloned().unwrap_or_else(|| dirs[0].clone())
    });
    let found = discover(&dir);
    if found.is_empty() {
        out!("no model series under {}", dir.display())?;
        return Ok(());
    }
    // By telescope: each series under every telescope its domain declares (the registry's
    // order, then others); series that declare none, which `auto` takes for any telescope, last.
    let usable: Vec<(&std::path::PathBuf, &crate::steps::series::Series)> =
        found.iter().filter_map(|(dir, s)| s.as_ref().ok().map(|s| (dir, s))).collect();
    let declared = |s: &crate::steps::series::Series| -> Vec<String> {
        let v = s.telescopes().to_vec();
        v.iter().map(|t| crate::steps::series::telescope_key(t)).collect()
    };
    let registry: Vec<String> = crate::simulate::telescope::telescopes()?.iter().map(|t| t.key.clone()).collect();
    let mut groups: Vec<String> = registry.clone();
    for (_, s) in &usable {
        for t in declared(s) {
            if !groups.contains(&t) {
                groups.push(t);
            }
        }
    }
    for group in &groups {
        let members: Vec<_> = usable.iter().filter(|(_, s)| declared(s).contains(group)).collect();
        if !members.is_empty() {
            out!("telescope {group}:")?;
            for (dir, s) in members {
                describe(dir, s)?;
            }
        }
    }
    let undeclared: Vec<_> = usable.iter().filter(|(_, s)| declared(s).is_empty()).collect();
    if !undeclared.is_empty() {
        out!("no telescope declared (`auto` may run these on any telescope's data):")?;
        for (dir, s) in undeclared {
            describe(dir, s)?;
        }
    }
    let without: Vec<&str> = registry.iter().filter(|k| !usable.iter().any(|(_, s)| s.trained_for_telescope(k))).map(String::as_str).collect();
    if !without.is_empty() {
        out!("telescopes the simulator knows without a series here: {} (`series: auto` images their data with the built-in CLEAN)", without.join(", "))?;
    }
    for (dir, series) in &found {
        if let Err(e) = series {
            out!("{}: unusable: {e}", dir.display())?;
        }
    }
    Ok(())
}

fn describe(dir: &std::path::Path, s: &crate::steps::series::Series) -> Result<()> {
    let arch = match s.architecture {
        Architecture::R2d2 => "R2D2".to_string(),
        Architecture::R3d3 => format!("R3D3, {} layers", s.layers()),
    };
    out!("  {}  ({})", dir.display(), s.name)?;
    let realisations = if s.realisations > 1 { format!(" x {} realisations", s.realisations) } else { String::new() };
    out!("    {} iterations{realisations}, {arch}; {}", s.len(), s.origin)?;
    let sizes = if s.image_sizes.is_empty() { "unknown".to_string() } else { format!("{:?}", s.image_sizes) };
    out!("    trained for image sizes {sizes}{}", if s.any_size { ", runs at any size" } else { " only" })?;
    if s.edge_padding > 0 {
        out!("    network inputs mirrored {} pixels past each image edge (outputs cropped)", s.edge_padding)?;
    }
    if !s.orientation_cycle.is_empty() {
        let turns: Vec<String> = s.orientation_cycle.iter().map(|o| serde_yaml::to_string(o).unwrap_or_default().trim().to_string()).collect();
        out!("    network k sees its images turned by entry (k - 1) mod {} of [{}]", turns.len(), turns.join(", "))?;
    }
    if let Some(sigmas) = s.auto_mask {
        out!("    its model is kept to where the data show emission (auto_mask {sigmas} unless the step sets one; 0: none)")?;
    }
    if s.early_stop_from > 1 {
        out!("    networks 1 to {} always run; the early stop (stalled, converged) applies from network {} on", s.early_stop_from - 1, s.early_stop_from)?;
    }
    let Some(m) = &s.manifest else { return Ok(()) };
    if !m.description.is_empty() {
        out!("    {}", m.description)?;
    }
    match &m.validity {
        Some(v) => out!("    domain: {}", v.summary())?,
        None => out!("    domain: not declared (jobs are not checked against it)")?,
    }
    let mut facts = Vec::new();
    if let Some(sr) = m.superresolution {
        facts.push(format!("own setting: super-resolution {sr}"));
    }
    if let Some([lo, hi]) = m.dynamic_range {
        facts.push(format!("dynamic range {lo:.0e}..{hi:.0e}"));
    }
    if !m.weighting.is_null() {
        facts.push(format!("weighting {}", serde_json::to_string(&m.weighting).unwrap_or_default()));
    }
    if !facts.is_empty() {
        out!("    {}", facts.join(", "))?;
    }
    if let Some(last) = m.test.as_sequence().and_then(|t| t.last()).or_else(|| m.validation.as_sequence().and_then(|v| v.last())) {
        out!("    last iteration metrics: {}", serde_json::to_string(last).unwrap_or_default())?;
    }
    Ok(())
}
