//! `r2d2 models`: the model series found under a directory (default `models/`), by the
//! telescope they were trained for, with their manifests' key facts.

use r2d2_imaging::steps::series::{discover, model_dirs, Architecture};
use r2d2_imaging::Result;
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
    // By telescope: the one each series declares in its domain (or manifest), in the order
    // the registry lists telescopes, then others; series that declare none last.
    let telescope_of = |s: &r2d2_imaging::steps::series::Series| {
        let m = s.manifest.as_ref();
        let declared = m.and_then(|m| m.validity.as_ref()).and_then(|v| v.telescopes.as_ref()).and_then(|t| t.first().cloned());
        declared.or_else(|| m.map(|m| m.telescope.clone()).filter(|t| !t.is_empty())).map(|t| r2d2_imaging::steps::series::telescope_key(&t))
    };
    let registry: Vec<String> = r2d2_imaging::simulate::telescope::telescopes()?.iter().map(|t| t.key.clone()).collect();
    let mut groups: Vec<Option<String>> = Vec::new();
    for (_, s) in &found {
        let key = s.as_ref().ok().and_then(|s| telescope_of(s));
        if s.is_ok() && !groups.contains(&key) {
            groups.push(key);
        }
    }
    groups.sort_by_key(|g| (g.is_none(), g.as_ref().map(|k| registry.iter().position(|r| r == k).unwrap_or(registry.len())), g.clone()));
    for group in &groups {
        match group {
            Some(t) => out!("telescope {t}:")?,
            None => out!("no telescope declared:")?,
        }
        for (dir, series) in &found {
            match series {
                Ok(s) if telescope_of(s) == *group => describe(dir, s)?,
                _ => {}
            }
        }
    }
    let without: Vec<&String> = registry.iter().filter(|k| !groups.contains(&Some((*k).clone()))).collect();
    if !without.is_empty() {
        let list: Vec<&str> = without.iter().map(|k| k.as_str()).collect();
        out!("telescopes the simulator knows without a series here: {} (`series: auto` images their data with the built-in CLEAN)", list.join(", "))?;
    }
    for (dir, series) in &found {
        if let Err(e) = series {
            out!("{}: unusable: {e}", dir.display())?;
        }
    }
    Ok(())
}

fn describe(dir: &std::path::Path, s: &r2d2_imaging::steps::series::Series) -> Result<()> {
    let arch = match s.architecture {
        Architecture::R2d2 => "R2D2".to_string(),
        Architecture::R3d3 => format!("R3D3, {} layers", s.layers()),
    };
    out!("  {}  ({})", dir.display(), s.name)?;
    let realisations = if s.realisations > 1 { format!(" x {} realisations", s.realisations) } else { String::new() };
    out!("    {} iterations{realisations}, {arch}; {}", s.len(), s.origin)?;
    let sizes = if s.image_sizes.is_empty() { "unknown".to_string() } else { format!("{:?}", s.image_sizes) };
    out!("    trained for image sizes {sizes}{}", if s.any_size { ", runs at any size" } else { " only" })?;
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
