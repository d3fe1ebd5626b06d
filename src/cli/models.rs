//! `r2d2 models`: the model series found under a directory (default `models/`), with their
//! manifests' key facts.

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
    for (dir, series) in found {
        match series {
            Err(e) => out!("{}: unusable: {e}", dir.display())?,
            Ok(s) => {
                let arch = match s.architecture {
                    Architecture::R2d2 => "R2D2".to_string(),
                    Architecture::R3d3 => format!("R3D3, {} layers", s.layers()),
                };
                out!("{}  ({})", dir.display(), s.name)?;
                let realisations = if s.realisations > 1 { format!(" x {} realisations", s.realisations) } else { String::new() };
                out!("  {} iterations{realisations}, {arch}; {}", s.len(), s.origin)?;
                let sizes = if s.image_sizes.is_empty() { "unknown".to_string() } else { format!("{:?}", s.image_sizes) };
                out!("  trained for image sizes {sizes}{}", if s.any_size { ", runs at any size" } else { " only" })?;
                if let Some(m) = &s.manifest {
                    if !m.description.is_empty() {
                        out!("  {}", m.description)?;
                    }
                    match &m.validity {
                        Some(v) => out!("  domain: {}", v.summary())?,
                        None => out!("  domain: not declared (jobs are not checked against it)")?,
                    }
                    let mut facts = Vec::new();
                    if !m.telescope.is_empty() {
                        facts.push(format!("telescope {}", m.telescope));
                    }
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
                        out!("  {}", facts.join(", "))?;
                    }
                    if let Some(last) = m.test.as_sequence().and_then(|t| t.last()).or_else(|| m.validation.as_sequence().and_then(|v| v.last())) {
                        out!("  last iteration metrics: {}", serde_json::to_string(last).unwrap_or_default())?;
                    }
                }
            }
        }
    }
    Ok(())
}
