//! A model series on disk: `models/<series>/manifest.yaml` and its ONNX files, or a directory
//! holding only the reference implementation's file names (no manifest), whose convention is
//! then inferred. Reading a series checks everything that can be checked without running a
//! network, so a broken series fails before imaging starts.

pub use crate::steps::error::SeriesError;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// A series content error as the crate's error.
fn invalid(path: impl AsRef<Path>, message: impl Into<String>) -> Error {
    SeriesError::Invalid { path: path.as_ref().to_path_buf(), message: message.into() }.into()
}

/// The manifest format this build reads.
pub const MANIFEST_FORMAT: u32 = 1;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Architecture {
    /// One U-Net per iteration.
    R2d2,
    /// Each iteration a component of J U-Net layers with PSF data-fidelity layers between them.
    R3d3,
}

/// `models/<series>/manifest.yaml`. Unknown keys are rejected so a typo is not silently ignored.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub format: u32,
    pub name: String,
    #[serde(default)]
    pub description: String,
    #[serde(default)]
    pub telescope: String,
    pub architecture: Architecture,
    #[serde(default)]
    pub network: serde_yaml::Value,
    /// Image sizes the series was trained for.
    pub image_sizes: Vec<usize>,
    /// Whether it may run at other sizes (the networks are fully convolutional).
    #[serde(default)]
    pub any_size: bool,
    #[serde(default)]
    pub superresolution: Option<f64>,
    #[serde(default)]
    pub weighting: serde_yaml::Value,
    #[serde(default)]
    pub dynamic_range: Option<[f64; 2]>,
    /// Only `reference` (network 1: `[dirty/a, 0]`, then `[x/a, r/a]`) exists today.
    pub input_convention: String,
    /// Only `mean` (`a` = mean of the previous estimate, of the dirty image at i = 1).
    pub normalisation: String,
    /// Network files in order; for R3D3 each entry lists the component's J layer files.
    #[serde(default)]
    pub networks: Vec<NetworkFiles>,
    /// Instead of `networks`: several independently trained realisations of the series, each
    /// listed as `networks` is; run one after the other, their mean is the image and their
    /// spread the uncertainty map.
    #[serde(default)]
    pub realisations: Vec<Vec<NetworkFiles>>,
    /// Where the series may be used; a job outside it is warned about (or refused, with the
    /// step's `validity: error`).
    #[serde(default)]
    pub validity: Option<Validity>,
    /// Layers per component (J) for R3D3; 1 for R2D2.
    #[serde(default = "one")]
    pub layers: usize,
    /// The network (1-based) from which the reference v2 early stop (residual ratio stalled or
    /// converged) may end the series; the networks before it always run (the divergence guard
    /// still stops a diverging series anywhere). The trainer sets it to the first network of a
    /// later training stage (a clean-up stage trained to trade a little residual for fewer
    /// artefacts), so that a stall in the stage before does not skip it. Default 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub early_stop_from: Option<usize>,
    /// Pixels by which each network's input is extended on every side, mirroring the image
    /// at its edges, and its output cropped back: a series whose networks make faint false
    /// emission along the image edges (their own zero padding) then makes it outside the
    /// image. Where set, `image size + 2 x edge_padding` must suit the networks (a multiple
    /// of 2^poolings for a U-Net). Default 0.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub edge_padding: usize,
    /// The orientation each network sees its images in, network k taking entry (k - 1) mod
    /// the list's length (R2D2 only): its inputs are turned so, and its output turned back.
    /// The networks' own artefacts (stripes, mottling) then lie differently from one network
    /// to the next and do not build up along one direction (training/README.md, "Orientation
    /// cycle"). Default: every network as trained.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub orientation_cycle: Vec<Orientation>,
    /// The emission mask (noise sigmas, as the step's `auto_mask`) the series runs with unless
    /// the step says otherwise, chosen on the validation sets: a series whose networks leave
    /// low ripples around compact sources then keeps them out of its model. Default: none (on
    /// an image more than twice its trained size across, a mask is on regardless).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub auto_mask: Option<f64>,
    #[serde(default)]
    pub provenance: serde_yaml::Value,
    #[serde(default)]
    pub validation: serde_yaml::Value,
    #[serde(default)]
    pub test: serde_yaml::Value,
}

fn one() -> usize {
    1
}

/// A symmetry of the square image grid: the turn network k's images are given in
/// (`orientation_cycle`). Image `f[y][x]` (row-major, `x` the column) is turned to `g`:
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Orientation {
    /// `g[y][x] = f[y][x]`.
    Identity,
    /// `g[y][x] = f[y][n-1-x]`: columns reversed.
    MirrorX,
    /// `g[y][x] = f[n-1-y][x]`: rows reversed.
    MirrorY,
    /// `g[y][x] = f[n-1-y][n-1-x]`: a half turn.
    #[serde(rename = "rotate_180")]
    Rotate180,
    /// `g[y][x] = f[x][y]`.
    Transpose,
    /// `g[y][x] = f[x][n-1-y]`: a quarter turn (columns reversed, then transposed).
    #[serde(rename = "rotate_90")]
    Rotate90,
    /// `g[y][x] = f[n-1-x][y]`: the opposite quarter turn (rows reversed, then transposed).
    #[serde(rename = "rotate_270")]
    Rotate270,
    /// `g[y][x] = f[n-1-x][n-1-y]`: the transpose about the other diagonal.
    AntiTranspose,
}

impl Orientation {
    /// The source pixel `(y, x)` of `f` that lands on `(y, x)` of the turned `n x n` image.
    fn source(self, y: usize, x: usize, n: usize) -> (usize, usize) {
        let last = n - 1;
        match self {
            Orientation::Identity => (y, x),
            Orientation::MirrorX => (y, last - x),
            Orientation::MirrorY => (last - y, x),
            Orientation::Rotate180 => (last - y, last - x),
            Orientation::Transpose => (x, y),
            Orientation::Rotate90 => (x, last - y),
            Orientation::Rotate270 => (last - x, y),
            Orientation::AntiTranspose => (last - x, last - y),
        }
    }

    /// The orientation that turns the image back.
    pub fn inverse(self) -> Orientation {
        match self {
            Orientation::Rotate90 => Orientation::Rotate270,
            Orientation::Rotate270 => Orientation::Rotate90,
            other => other,
        }
    }

    /// Each row-major `n x n` image of a stack (`images.len()` a multiple of `n * n`) turned
    /// to this orientation; the identity hands the stack back as it is.
    pub fn apply<T: Copy>(self, images: Vec<T>, n: usize) -> Vec<T> {
        assert!(n > 0 && images.len().is_multiple_of(n * n), "a stack of n x n images");
        if self == Orientation::Identity {
            return images;
        }
        let mut out = Vec::with_capacity(images.len());
        for image in images.chunks_exact(n * n) {
            for y in 0..n {
                out.extend((0..n).map(|x| {
                    let (sy, sx) = self.source(y, x, n);
                    image[sy * n + sx]
                }));
            }
        }
        out
    }
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// The observations a series was trained for (`validity:` in the manifest: its domain).
/// The trainer writes it from the training sets, the importer from the reference's published
/// ranges. Telescope, super-resolution, weighting, robustness, track length and integration
/// time are checked against each job; the image sizes by [`Series::check_size`]; the dynamic
/// range is recorded for `r2d2 models`.
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Validity {
    /// Telescopes whose observations it was trained on (`vla`, `meerkat`, ...).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub telescopes: Option<Vec<String>>,
    /// Image sizes it serves: those it was trained at (the manifest's `image_sizes`) and any
    /// other it was measured at on held-out data and found the best series for (`auto` then
    /// chooses it there as at a trained size; off-size handling, such as the weighting on its
    /// trained field's grid, stays as at any other size).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_sizes: Option<Vec<usize>>,
    /// Super-resolution factors `[min, max]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub superresolution: Option<[f64; 2]>,
    /// Briggs robustness `[min, max]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robust: Option<[f64; 2]>,
    /// Weighting schemes (`briggs`, `uniform`, `natural`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub weighting: Option<Vec<String>>,
    /// Target dynamic ranges of the training skies `[min, max]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dynamic_range: Option<[f64; 2]>,
    /// Total track lengths, hours `[min, max]`: training observes a sample's configurations one
    /// after the other and counts their sum (as [`crate::vis::ObservedTimes`] measures a job's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub track_hours: Option<[f64; 2]>,
    /// Integration times, seconds `[min, max]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub integration_s: Option<[f64; 2]>,
}

/// Relative tolerance on the super-resolution range: a pixel chosen in arcseconds rarely gives
/// exactly the trained factor, and a few per cent finer or coarser sampling of the longest
/// baseline is not a different problem for the networks.
pub const SUPERRESOLUTION_TOLERANCE: f64 = 0.05;

/// Relative tolerance on the track-length range: a track some minutes shorter or longer
/// (a late start, calibrator scans within it) covers nearly the same hour angles.
pub const TRACK_TOLERANCE: f64 = 0.1;

/// Relative tolerance on the integration-time range: dump times are set in round seconds
/// near, not at, the trained sampling.
pub const INTEGRATION_TOLERANCE: f64 = 0.05;

/// What a job's imaging is, as far as a series' validity goes (unknown parts are not checked).
#[derive(Clone, Debug, Default)]
pub struct ImagingSetup {
    pub superresolution: Option<f64>,
    pub weighting: Option<String>,
    pub robust: Option<f64>,
    /// The telescope the data come from (an MS's `OBSERVATION::TELESCOPE_NAME`, a table's
    /// `telescope` metadata).
    pub telescope: Option<String>,
    /// Hours the source was tracked, summed over the data's tracks (known once the data are
    /// read, where they carry times).
    pub track_hours: Option<f64>,
    /// Integration time of the data, seconds (likewise).
    pub integration_s: Option<f64>,
}

/// A trained range in words: `range 1.5..2.5`, or `setting 0` where it is one value.
fn span([lo, hi]: [f64; 2]) -> String {
    if lo == hi {
        format!("setting {lo} (the only one it was trained at)")
    } else {
        format!("range {lo}..{hi}")
    }
}

/// A trained range with a unit after the values and what the values are: `range 8..12 h (the
/// hours ...)`, `setting 300 s (the ...)`.
fn span_of([lo, hi]: [f64; 2], unit: &str, what: &str) -> String {
    if lo == hi {
        format!("setting {lo}{unit} ({what})")
    } else {
        format!("range {lo}..{hi}{unit} ({what})")
    }
}

/// `range` widened by `tolerance` of its ends (relative).
fn widened([lo, hi]: [f64; 2], tolerance: f64) -> [f64; 2] {
    [lo * (1.0 - tolerance), hi * (1.0 + tolerance)]
}

/// A telescope name as series compare them: the key of the telescope it names in the telescope
/// data (`data/telescopes/telescopes.yaml`: by its key, name or an alias, so that the VLA's
/// `EVLA`, as CASA writes it, is `vla`), else the name in lower case.
pub fn telescope_key(name: &str) -> String {
    let name = name.trim();
    let known = crate::simulate::telescope::telescopes().ok().and_then(|all| all.iter().find(|t| t.is_named(name)));
    known.map_or_else(|| name.to_ascii_lowercase(), |t| t.key.clone())
}

impl Validity {
    /// The domain in one line, for `r2d2 models` and warnings.
    pub fn summary(&self) -> String {
        let range = |r: [f64; 2]| if r[0] == r[1] { format!("{}", r[0]) } else { format!("{}..{}", r[0], r[1]) };
        let mut parts = Vec::new();
        if let Some(t) = &self.telescopes {
            parts.push(format!("telescope {}", t.join("/")));
        }
        if let Some(s) = &self.image_sizes {
            parts.push(format!("size {}", s.iter().map(|s| s.to_string()).collect::<Vec<_>>().join("/")));
        }
        if let Some(r) = self.superresolution {
            parts.push(format!("SR {}", range(r)));
        }
        match (&self.weighting, self.robust) {
            (Some(w), Some(r)) if w.iter().any(|w| w == "briggs") => parts.push(format!("{} robust {}", w.join("/"), range(r))),
            (Some(w), _) => parts.push(w.join("/")),
            (None, Some(r)) => parts.push(format!("robust {}", range(r))),
            _ => {}
        }
        if let Some([lo, hi]) = self.dynamic_range {
            parts.push(format!("DR {lo:.0e}..{hi:.0e}"));
        }
        if let Some(r) = self.track_hours {
            parts.push(format!("tracks {} h", range(r)));
        }
        if let Some(r) = self.integration_s {
            parts.push(format!("integration {} s", range(r)));
        }
        parts.join(", ")
    }
}

#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(untagged)]
pub enum NetworkFiles {
    One(PathBuf),
    Layers(Vec<PathBuf>),
}

/// The files of one `networks` entry (`key`, e.g. `networks[3]`), checked to be paths inside the
/// series directory and to match the architecture.
fn manifest_entry(dir: &Path, path: &Path, manifest: &Manifest, key: &str, entry: &NetworkFiles) -> Result<Vec<PathBuf>> {
    // Entries are relative paths down from the series directory, checked before any file is
    // opened (`../../../etc/passwd` was).
    let names: Vec<&PathBuf> = match entry {
        NetworkFiles::One(f) => vec![f],
        NetworkFiles::Layers(fs) => fs.iter().collect(),
    };
    for name in names {
        let inside = name.components().all(|c| matches!(c, std::path::Component::Normal(_) | std::path::Component::CurDir));
        if !inside || name.as_os_str().is_empty() {
            let name = name.display();
            return Err(invalid(path, format!("{key}: '{name}' must be a path inside the series directory (no '..', not absolute)")));
        }
    }
    let layers = manifest.layers;
    match (entry, manifest.architecture) {
        (NetworkFiles::One(f), Architecture::R2d2) => Ok(vec![dir.join(f)]),
        (NetworkFiles::Layers(fs), Architecture::R3d3) if fs.len() == layers => Ok(fs.iter().map(|f| dir.join(f)).collect()),
        (NetworkFiles::Layers(fs), Architecture::R3d3) => Err(invalid(path, format!("{key}: expected {layers} layer files (layers: {layers}), got {}", fs.len()))),
        (NetworkFiles::One(_), Architecture::R3d3) => Err(invalid(path, format!("{key}: an r3d3 series lists the {layers} layer files of each component"))),
        (NetworkFiles::Layers(_), Architecture::R2d2) => Err(invalid(path, format!("{key}: an r2d2 series lists one file per network"))),
    }
}

/// A series ready to run: the files of each iteration, checked to exist.
#[derive(Clone, Debug)]
pub struct Series {
    pub dir: PathBuf,
    pub name: String,
    pub architecture: Architecture,
    /// `files[i]`: the network(s) of iteration i + 1 (one for R2D2, J layers for R3D3); with
    /// several realisations, theirs one after the other ([`Series::realisation`]).
    pub files: Vec<Vec<PathBuf>>,
    /// Independently trained realisations (1 for most series).
    pub realisations: usize,
    pub image_sizes: Vec<usize>,
    pub any_size: bool,
    /// The manifest's `early_stop_from` (1 without one).
    pub early_stop_from: usize,
    /// The manifest's `edge_padding` (0 without one).
    pub edge_padding: usize,
    /// The manifest's `orientation_cycle` (empty: every network as trained).
    pub orientation_cycle: Vec<Orientation>,
    /// The manifest's `auto_mask` (none without one).
    pub auto_mask: Option<f64>,
    pub manifest: Option<Manifest>,
    /// How the series was read (for the log and `r2d2 models`).
    pub origin: String,
}

impl Series {
    /// Read the series in `dir`: its manifest, or else the reference file names.
    pub fn open(dir: &Path) -> Result<Series> {
        if !dir.is_dir() {
            return Err(invalid(dir, "expected a model series directory (manifest.yaml and ONNX files, or R2D2_UNet_N{i}.onnx files)"));
        }
        let manifest_path = dir.join("manifest.yaml");
        let series = if manifest_path.exists() { Series::from_manifest(dir, &manifest_path)? } else { Series::infer(dir)? };
        // Through links too: a series reads only files of its own directory.
        let canonical_dir = dir.canonicalize().map_err(|e| Error::io(dir, e))?;
        for file in series.files.iter().flatten() {
            let size = match std::fs::metadata(file) {
                Ok(m) if m.is_file() => m.len(),
                Ok(m) => {
                    let kind = crate::error::file_kind(&m);
                    return Err(invalid(file, format!("network file of series '{}' is {kind}, not a regular file (expected an ONNX network)", series.name)));
                }
                Err(source) => {
                    return Err(SeriesError::MissingNetwork { path: file.clone(), series: series.name.clone(), source: Some(source) }.into());
                }
            };
            let canonical = file.canonicalize().map_err(|e| Error::io(file, e))?;
            if !canonical.starts_with(&canonical_dir) {
                return Err(invalid(file, format!("network file of series '{}' leads outside the series directory (to {})", series.name, canonical.display())));
            }
            if size == 0 {
                return Err(invalid(file, format!("network file of series '{}' is empty (0 bytes): not a network", series.name)));
            }
        }
        Ok(series)
    }

    fn from_manifest(dir: &Path, path: &Path) -> Result<Series> {
        let metadata = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
        if !metadata.is_file() {
            return Err(invalid(path, format!("the manifest is {}, not a regular file (expected YAML)", crate::error::file_kind(&metadata))));
        }
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let de = serde_yaml::Deserializer::from_str(&text);
        let manifest: Manifest = serde_path_to_error::deserialize(de).map_err(|e| {
            let at = e.path().to_string();
            let source = e.into_inner();
            let line = source.location().map(|l| format!("line {}, column {}", l.line(), l.column()));
            let key = (at != ".").then_some(at);
            let place = line.into_iter().chain(key).collect::<Vec<_>>().join(": ");
            SeriesError::Manifest { path: path.to_path_buf(), place, source }
        })?;
        if manifest.format != MANIFEST_FORMAT {
            return Err(invalid(path, format!("format: expected manifest format {MANIFEST_FORMAT}, got {} (written by a different version of r2d2?)", manifest.format)));
        }
        if manifest.input_convention != "reference" {
            return Err(invalid(path, format!("input_convention: expected 'reference', got '{}'", manifest.input_convention)));
        }
        if manifest.normalisation != "mean" {
            return Err(invalid(path, format!("normalisation: expected 'mean', got '{}'", manifest.normalisation)));
        }
        if let Some(v) = &manifest.validity {
            // A NaN bound compares false with everything and switched the domain check off; a
            // reversed range warned on every job (issue 56.11).
            let ranges = [("superresolution", v.superresolution), ("robust", v.robust), ("dynamic_range", v.dynamic_range), ("track_hours", v.track_hours), ("integration_s", v.integration_s)];
            for (key, range) in ranges {
                if let Some([low, high]) = range.filter(|[low, high]| !(low.is_finite() && high.is_finite() && low <= high)) {
                    return Err(invalid(path, format!("validity.{key}: expected a range [min, max] of finite numbers with min <= max, got [{low}, {high}]")));
                }
            }
        }
        if !manifest.orientation_cycle.is_empty() && manifest.architecture != Architecture::R2d2 {
            // R3D3's data-fidelity layers between the networks would need the PSF turned too.
            return Err(invalid(path, "orientation_cycle: only an R2D2 series may turn its networks' images"));
        }
        let lists: Vec<(String, &Vec<NetworkFiles>)> = match (manifest.networks.is_empty(), manifest.realisations.is_empty()) {
            (false, true) => vec![("networks".to_string(), &manifest.networks)],
            (true, false) => manifest.realisations.iter().enumerate().map(|(r, list)| (format!("realisations[{r}]"), list)).collect(),
            (true, true) => return Err(invalid(path, "networks: expected at least one network file (or realisations: one list per realisation)")),
            (false, false) => return Err(invalid(path, "networks and realisations: give one of them (realisations lists the networks of each realisation)")),
        };
        if manifest.layers == 0 {
            return Err(invalid(path, "layers: expected at least 1"));
        }
        let per_realisation = lists[0].1.len();
        if let Some(s) = manifest.auto_mask.filter(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(invalid(path, format!("auto_mask: expected a positive number of noise sigmas, got {s}")));
        }
        if let Some(from) = manifest.early_stop_from.filter(|&f| f == 0 || f > per_realisation) {
            return Err(invalid(path, format!("early_stop_from: expected a network of the series, 1 to {per_realisation}, got {from}")));
        }
        let mut files = Vec::new();
        for (key, list) in &lists {
            if list.len() != lists[0].1.len() || list.is_empty() {
                return Err(invalid(path, format!("{key}: expected {} networks, as every realisation has, got {}", lists[0].1.len(), list.len())));
            }
            for (i, entry) in list.iter().enumerate() {
                files.push(manifest_entry(dir, path, &manifest, &format!("{key}[{i}]"), entry)?);
            }
        }
        Ok(Series {
            dir: dir.to_path_buf(),
            name: manifest.name.clone(),
            architecture: manifest.architecture,
            files,
            image_sizes: manifest.image_sizes.clone(),
            any_size: manifest.any_size,
            early_stop_from: manifest.early_stop_from.unwrap_or(1),
            edge_padding: manifest.edge_padding,
            orientation_cycle: manifest.orientation_cycle.clone(),
            auto_mask: manifest.auto_mask,
            realisations: lists.len(),
            origin: format!("manifest {}", path.display()),
            manifest: Some(manifest),
        })
    }

    /// A directory laid out like the reference implementation's releases:
    /// `R2D2_UNet_N{i}.onnx`, or `R3D3_R2D2Net_{J}Layers_N{i}/R3D3_R2D2Net_{J}Layers_N{i}_L{l}.onnx`.
    fn infer(dir: &Path) -> Result<Series> {
        let entries: Vec<String> = std::fs::read_dir(dir)
            .map_err(|e| Error::io(dir, e))?
            .filter_map(|e| e.ok().map(|e| e.file_name().to_string_lossy().into_owned()))
            .collect();
        let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let numbered = |prefix: &str, suffix: &str| -> Vec<usize> {
            let mut ns: Vec<usize> = entries
                .iter()
                .filter_map(|e| e.strip_prefix(prefix).and_then(|r| r.strip_suffix(suffix)).and_then(|n| n.parse().ok()))
                .collect();
            ns.sort_unstable();
            ns
        };
        let r2d2 = numbered("R2D2_UNet_N", ".onnx");
        let r3d3: Vec<(usize, usize)> = entries
            .iter()
            .filter_map(|e| {
                let rest = e.strip_prefix("R3D3_R2D2Net_")?;
                let (j, rest) = rest.split_once("Layers_N")?;
                Some((j.parse().ok()?, rest.parse().ok()?))
            })
            .collect();
        let contiguous = |ns: &[usize]| ns.iter().enumerate().all(|(k, &n)| n == k + 1);
        if !r2d2.is_empty() {
            if !contiguous(&r2d2) {
                return Err(invalid(dir, format!("expected R2D2_UNet_N1.onnx .. N{}.onnx without gaps, found networks {r2d2:?}", r2d2.len())));
            }
            let files = r2d2.iter().map(|i| vec![dir.join(format!("R2D2_UNet_N{i}.onnx"))]).collect();
            return Ok(Series {
                dir: dir.to_path_buf(),
                name,
                architecture: Architecture::R2d2,
                files,
                image_sizes: Vec::new(),
                any_size: true,
                early_stop_from: 1,
                edge_padding: 0,
                orientation_cycle: Vec::new(),
                auto_mask: None,
                realisations: 1,
                manifest: None,
                origin: "reference file names R2D2_UNet_N{i}.onnx (no manifest)".into(),
            });
        }
        if !r3d3.is_empty() {
            let j = r3d3[0].0;
            if r3d3.iter().any(|&(jj, _)| jj != j) {
                return Err(invalid(dir, "expected R3D3 components with one layer count J, found several"));
            }
            let mut ns: Vec<usize> = r3d3.iter().map(|&(_, n)| n).collect();
            ns.sort_unstable();
            if !contiguous(&ns) {
                return Err(invalid(dir, format!("expected R3D3 components N1 .. N{} without gaps, found {ns:?}", ns.len())));
            }
            let files = ns
                .iter()
                .map(|i| {
                    let sub = format!("R3D3_R2D2Net_{j}Layers_N{i}");
                    (1..=j).map(|l| dir.join(&sub).join(format!("{sub}_L{l}.onnx"))).collect()
                })
                .collect();
            return Ok(Series {
                dir: dir.to_path_buf(),
                name,
                architecture: Architecture::R3d3,
                files,
                image_sizes: Vec::new(),
                any_size: true,
                early_stop_from: 1,
                edge_padding: 0,
                orientation_cycle: Vec::new(),
                auto_mask: None,
                realisations: 1,
                manifest: None,
                origin: format!("reference file names R3D3_R2D2Net_{j}Layers_N{{i}} (no manifest)"),
            });
        }
        Err(invalid(
            dir,
            "no manifest.yaml and no network files with the reference names (R2D2_UNet_N{i}.onnx or R3D3_R2D2Net_{J}Layers_N{i}/...)",
        ))
    }

    /// Iterations (networks or R3D3 components) of one realisation.
    pub fn len(&self) -> usize {
        self.files.len() / self.realisations.max(1)
    }

    /// The files of realisation `r` (0-based), `[iteration - 1][layer]`.
    pub fn realisation(&self, r: usize) -> &[Vec<PathBuf>] {
        &self.files[r * self.len()..(r + 1) * self.len()]
    }

    /// Where the job lies outside the manifest's `validity`, one sentence per problem (empty
    /// when it lies inside, or the series states no validity).
    pub fn validity_problems(&self, job: &ImagingSetup) -> Vec<String> {
        let Some(v) = self.manifest.as_ref().and_then(|m| m.validity.as_ref()) else { return Vec::new() };
        let mut problems = Vec::new();
        let outside = |x: f64, [lo, hi]: [f64; 2]| x < lo - 1e-9 || x > hi + 1e-9;
        if let (Some(telescopes), Some(telescope)) = (&v.telescopes, &job.telescope) {
            let key = telescope_key(telescope);
            // Data that name no telescope are not checked against one.
            if !key.is_empty() && key != crate::vis::UNKNOWN_TELESCOPE && !telescopes.iter().any(|t| telescope_key(t) == key) {
                problems.push(format!("the data come from the telescope '{telescope}', and the series was trained for {}", telescopes.join(", ")));
            }
        }
        if let (Some(range), Some(sr)) = (v.superresolution, job.superresolution) {
            let [lo, hi] = range;
            if outside(sr, widened([lo, hi], SUPERRESOLUTION_TOLERANCE)) {
                problems.push(format!("super-resolution {sr:.3} (the pixel samples the longest baseline {sr:.3} times finer than Nyquist) is outside the series' {}", span(range)));
            }
        }
        if let (Some(schemes), Some(scheme)) = (&v.weighting, &job.weighting) {
            if !schemes.iter().any(|s| s.eq_ignore_ascii_case(scheme)) {
                problems.push(format!("weighting '{scheme}' is not one the series was trained for ({})", schemes.join(", ")));
            }
        }
        let briggs = job.weighting.as_deref().is_some_and(|s| s.eq_ignore_ascii_case("briggs"));
        if let (Some(range), Some(robust), true) = (v.robust, job.robust, briggs) {
            if outside(robust, range) {
                problems.push(format!("Briggs robust {robust} is outside the series' {}", span(range)));
            }
        }
        if let (Some(range), Some(hours)) = (v.track_hours, job.track_hours) {
            if outside(hours, widened(range, TRACK_TOLERANCE)) {
                problems.push(format!(
                    "a track of {hours:.1} h (the hours the data's source was tracked, summed over its tracks) is outside the series' {}",
                    span_of(range, " h", "the hours of observation it was trained on")
                ));
            }
        }
        // Only a longer integration: a shorter one samples the same tracks more densely (real
        // dumps are seconds long), a longer one smears and thins them.
        if let (Some(range), Some(seconds)) = (v.integration_s, job.integration_s) {
            if seconds > widened(range, INTEGRATION_TOLERANCE)[1] {
                problems.push(format!(
                    "an integration time of {seconds} s is longer than the series' {}",
                    span_of(range, " s", "the sampling of the tracks it was trained on")
                ));
            }
        }
        problems
    }

    /// How far `job`'s setting lies outside the declared domain: the super-resolution's, track
    /// length's and integration time's distances from their ranges relative to the range's
    /// nearer end, plus the Briggs robust's distance from its range (0 inside, or where the
    /// domain declares none), plus 100 for each problem no distance measures (telescope,
    /// weighting scheme): those come first.
    pub fn domain_distance(&self, job: &ImagingSetup) -> f64 {
        let Some(v) = self.manifest.as_ref().and_then(|m| m.validity.as_ref()) else { return 0.0 };
        let beyond = |x: f64, [lo, hi]: [f64; 2]| (lo - x).max(x - hi).max(0.0);
        let relative = |range: Option<[f64; 2]>, x: Option<f64>| match (range, x) {
            (Some([lo, hi]), Some(x)) => beyond(x, [lo, hi]) / (if x > hi { hi } else { lo }).max(f64::MIN_POSITIVE),
            _ => 0.0,
        };
        let longer = |range: Option<[f64; 2]>, x: Option<f64>| if x > range.map(|[_, hi]| hi) { relative(range, x) } else { 0.0 };
        let measured = relative(v.superresolution, job.superresolution) + relative(v.track_hours, job.track_hours) + longer(v.integration_s, job.integration_s);
        let unmeasured = ImagingSetup { superresolution: None, robust: None, track_hours: None, integration_s: None, ..job.clone() };
        let mismatches = self.validity_problems(&unmeasured).len() as f64;
        let briggs = job.weighting.as_deref().is_some_and(|s| s.eq_ignore_ascii_case("briggs"));
        let robust = match (v.robust, job.robust, briggs) {
            (Some(range), Some(robust), true) => beyond(robust, range),
            _ => 0.0,
        };
        100.0 * mismatches + measured + robust
    }

    /// Whether the series was trained for data of `telescope` (it declares that telescope,
    /// or declares none).
    pub fn trained_for_telescope(&self, telescope: &str) -> bool {
        self.validity_problems(&ImagingSetup { telescope: Some(telescope.to_string()), ..ImagingSetup::default() }).is_empty()
    }

    /// The telescopes the series' domain declares (none: it declares none, and may run on
    /// any telescope's data).
    pub fn telescopes(&self) -> &[String] {
        self.manifest.as_ref().and_then(|m| m.validity.as_ref()).and_then(|v| v.telescopes.as_deref()).unwrap_or_default()
    }

    /// The name and the telescopes it was trained for: `vla-r2d2-512 (vla)`.
    pub fn name_with_telescopes(&self) -> String {
        match self.telescopes() {
            [] => self.name.clone(),
            t => format!("{} ({})", self.name, t.join("/")),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }

    /// Layers per iteration (1 for R2D2).
    pub fn layers(&self) -> usize {
        self.files.first().map_or(1, |f| f.len())
    }

    /// The trained image size nearest to `size` by ratio, as `auto` measures it (the larger of
    /// two as near); `None` for a series that names none.
    pub fn nearest_trained_size(&self, size: usize) -> Option<usize> {
        self.image_sizes.iter().copied().min_by(|&a, &b| size_ratio_distance(a, size).total_cmp(&size_ratio_distance(b, size)).then(b.cmp(&a)))
    }

    /// Whether `auto` may choose the series for `size x size` images: it was trained at that
    /// size, or its domain names the size (measured there on held-out data).
    pub fn serves_size(&self, size: usize) -> bool {
        let declared = self.manifest.as_ref().and_then(|m| m.validity.as_ref()).and_then(|v| v.image_sizes.as_deref()).unwrap_or_default();
        self.image_sizes.contains(&size) || declared.contains(&size)
    }

    /// Whether the series may image `size x size` pixels; `Ok(Some(warning))` when it runs at a
    /// size nobody vouched for.
    pub fn check_size(&self, size: usize) -> Result<Option<String>> {
        // A U-Net halves the image at each pooling: other sizes fail inside the runtime, late
        // and with a raw shape error.
        let poolings = self.manifest.as_ref().and_then(|m| m.network.get("poolings")).and_then(serde_yaml::Value::as_u64);
        if let Some(multiple) = poolings.and_then(|p| u32::try_from(p).ok()).and_then(|p| 1usize.checked_shl(p)) {
            if size % multiple != 0 {
                return Err(invalid(
                    self.dir.join("manifest.yaml"),
                    format!("series '{}' pools {} times (network.poolings): the image size must be a multiple of {multiple}, got {size}", self.name, multiple.trailing_zeros()),
                ));
            }
        }
        if self.serves_size(size) {
            return Ok(None);
        }
        let trained = if self.image_sizes.is_empty() {
            "an unknown size (no manifest)".to_string()
        } else {
            format!("{:?}", self.image_sizes)
        };
        if !self.any_size {
            return Err(invalid(
                self.dir.join("manifest.yaml"),
                format!("series '{}' was trained for image sizes {trained} and does not allow others (any_size: false), but the pipeline images {size} x {size}", self.name),
            ));
        }
        Ok(Some(format!("series '{}' was trained for {trained}; running it at {size} x {size}", self.name)))
    }
}

/// How far a trained size is from an image size: `|ln(trained / size)|`.
fn size_ratio_distance(trained: usize, size: usize) -> f64 {
    (trained as f64 / size as f64).ln().abs()
}

/// The value of a step's `series` (and the default of `r2d2 image --step`) that picks the
/// series by the job's image size and imaging setting ([`select_for`]).
pub const AUTO_SERIES: &str = "auto";

/// The project's own series, preferred in this order when several serve a size.
pub const PROJECT_SERIES: [&str; 4] = ["vla-r2d2-512", "vla-r2d2-128", "vla-r2d2-512-broad", "meerkat-r2d2-512"];

/// The series for `size x size` images when none is named, among the series found in
/// [`model_dirs`]: of those that serve `size` ([`Series::serves_size`]: trained at it, or
/// measured there on held-out data), the first (the
/// project's own first, then by name) whose declared domain holds `setup` (what the pipeline
/// fixes: weighting, a super-resolution factor), else the one of the data's telescope whose
/// domain comes nearest to it ([`Series::domain_distance`]), else the first of them, whose
/// domain warning the job then carries, unless a series of the data's telescope may run off
/// its trained size (the telescope counts before the size); failing any, the
/// series that allows other sizes and was trained nearest to `size` (by ratio, the data's
/// telescope first), with a warning that it runs at a size it was not trained for.
pub fn select_for(size: usize, setup: &ImagingSetup) -> Result<(PathBuf, Option<String>)> {
    select_in(&model_dirs(), size, setup)
}

/// The usable series found in [`model_dirs`] (the first of each name), in the order `auto`
/// prefers them.
pub fn found_series() -> Result<Vec<(PathBuf, Series)>> {
    ranked_series(&model_dirs())
}

/// The usable series under `roots` (the first of each name: an earlier directory's series
/// stands before a later one's of the same name), the project's own first in
/// [`PROJECT_SERIES`] order, then by name. Two series of one name in one directory are an
/// error naming both: nothing says which the name means.
fn ranked_series(roots: &[PathBuf]) -> Result<Vec<(PathBuf, Series)>> {
    let mut found: Vec<(PathBuf, Series)> = Vec::new();
    for root in roots {
        let opened = open_all(root);
        for (k, (dir, series)) in opened.iter().enumerate() {
            if let (Ok(series), Some(other)) = (series, sharing_the_name(&opened, k)) {
                return Err(shared_name_error(dir, &series.name, other));
            }
        }
        for (dir, series) in opened {
            let Ok(series) = series else { continue };
            if !series.is_empty() && !found.iter().any(|(_, s)| s.name == series.name) {
                found.push((dir, series));
            }
        }
    }
    let rank = |s: &Series| (PROJECT_SERIES.iter().position(|p| *p == s.name).unwrap_or(PROJECT_SERIES.len()), s.name.clone());
    found.sort_by_key(|(_, s)| rank(s));
    Ok(found)
}

fn select_in(roots: &[PathBuf], size: usize, setup: &ImagingSetup) -> Result<(PathBuf, Option<String>)> {
    let found = ranked_series(roots)?;
    let trained: Vec<&(PathBuf, Series)> = found.iter().filter(|(_, s)| s.serves_size(size)).collect();
    // A series of the data's telescope outside its settings before one of another telescope.
    let same_telescope = |s: &Series| setup.telescope.as_deref().map_or(true, |t| s.trained_for_telescope(t));
    let fits = trained.iter().find(|(_, s)| s.validity_problems(setup).is_empty());
    // Where none holds the setting: of the data's telescope, the one whose domain comes
    // nearest to it (Briggs 1.5 is nearer the broad series' -1..1 than the narrow one's -1..0),
    // the higher ranked of equals.
    let nearest_domain = trained
        .iter()
        .filter(|(_, s)| same_telescope(s))
        .min_by(|a, b| a.1.domain_distance(setup).total_cmp(&b.1.domain_distance(setup)));
    // The series that may run off their trained sizes.
    let resizable: Vec<&(PathBuf, Series)> = found.iter().filter(|(_, s)| s.any_size && !s.image_sizes.is_empty()).collect();
    // The data's telescope counts before the size: a series of another telescope that serves
    // the size only where none trained for the data's telescope (declaring it) may run off its
    // trained size.
    let trained_for_it = |s: &Series| !s.telescopes().is_empty() && same_telescope(s);
    let of_telescope_off_size = setup.telescope.is_some() && resizable.iter().any(|(_, s)| trained_for_it(s));
    let any_serving = trained.first().filter(|_| !of_telescope_off_size);
    if let Some((dir, s)) = fits.or(nearest_domain).or(any_serving) {
        match trained.first() {
            Some((_, first)) if first.name != s.name => log::info!(
                "series '{}' chosen for {size} x {size}: '{}' was not trained for this setting ({})",
                s.name,
                first.name,
                first.validity_problems(setup).join("; ")
            ),
            _ if s.image_sizes.contains(&size) => log::info!("series '{}' chosen for {size} x {size} (trained for {:?})", s.name, s.image_sizes),
            _ => log::info!("series '{}' chosen for {size} x {size} (trained for {:?}, measured at {size} x {size} on held-out data)", s.name, s.image_sizes),
        }
        return Ok((dir.clone(), None));
    }
    let distance = |s: &Series| s.nearest_trained_size(size).map_or(f64::INFINITY, |t| size_ratio_distance(t, size));
    // `found` is in rank order and min_by keeps the first of equals: ties go to the higher rank.
    // The data's telescope counts before the size: its PSFs are what the networks learnt.
    // Among the nearest, one whose domain holds the setting, then the rank, as at the trained
    // size: weighted on its trained field's grid, `vla-r2d2-512` held at 1024 x 1024 where
    // the broad series lost a validation sky (training/README.md, "Off the trained size").
    let preference = |s: &Series| (distance(s), !s.validity_problems(setup).is_empty());
    let nearest = |of_telescope: bool| {
        resizable.iter().copied().filter(|(_, s)| !of_telescope || same_telescope(s)).min_by(|a, b| {
            let (pa, pb) = (preference(&a.1), preference(&b.1));
            pa.0.total_cmp(&pb.0).then(pa.1.cmp(&pb.1))
        })
    };
    let nearest = nearest(true).or_else(|| nearest(false));
    match nearest {
        Some((dir, s)) => Ok((
            dir.clone(),
            Some(format!("no series was trained for {size} x {size}; using '{}', trained for {:?} (images at other sizes are less precise)", s.name, s.image_sizes)),
        )),
        None => {
            let looked: Vec<String> = roots.iter().map(|d| d.display().to_string()).collect();
            let message = format!("no model series for {size} x {size} images in {} (set R2D2_MODELS, or name a series)", looked.join(", "));
            Err(SeriesError::NotFound { name: PathBuf::from(AUTO_SERIES), message }.into())
        }
    }
}

/// A series found in [`model_dirs`], other than `except`, that serves `size x size` images and
/// declaring a domain that holds `setup`: what a warning about a job outside its series' domain
/// can point to (the project's own first, then by name).
pub fn covering_series(size: usize, setup: &ImagingSetup, except: &str) -> Option<String> {
    found_series().ok()?.into_iter().map(|(_, s)| s).find_map(|s| {
        let declares = s.manifest.as_ref().is_some_and(|m| m.validity.is_some());
        let covers = s.name != except && declares && s.serves_size(size) && s.validity_problems(setup).is_empty();
        covers.then_some(s.name)
    })
}

/// The series directory for a step's `series` value, image size and imaging setting:
/// [`select_for`] for [`AUTO_SERIES`], else [`resolve`].
pub fn resolve_for(series: &Path, size: usize, setup: &ImagingSetup) -> Result<PathBuf> {
    let (dir, warning) = choose_for(series, size, setup)?;
    if let Some(w) = warning {
        log::warn!("{w}");
    }
    Ok(dir)
}

/// [`resolve_for`]'s series directory and `auto`'s off-size warning, not logged (a stage
/// before the step that needs to know the series; the step says the warning).
pub fn choose_for(series: &Path, size: usize, setup: &ImagingSetup) -> Result<(PathBuf, Option<String>)> {
    if series.as_os_str() == AUTO_SERIES {
        return select_for(size, setup);
    }
    Ok((resolve(series)?, None))
}

/// Directories an embedding host ships series in (the Python package's own `models/`), looked
/// up after the built-in places ([`add_model_dir`]).
static HOST_MODEL_DIRS: std::sync::RwLock<Vec<PathBuf>> = std::sync::RwLock::new(Vec::new());

/// Add a directory of series to look up after the built-in places (an embedding host's own,
/// such as the series an installed Python package ships).
pub fn add_model_dir(dir: PathBuf) {
    if let Ok(mut dirs) = HOST_MODEL_DIRS.write() {
        if !dirs.contains(&dir) {
            dirs.push(dir);
        }
    }
}

/// Where series are looked up by name, in order: `$R2D2_MODELS` alone when set; else `models/`
/// in the working directory, the repository's `models/` for a binary built in it
/// (`target/<profile>/r2d2`), `share/r2d2-imaging/models` beside an installed `bin/r2d2`, and
/// the directories an embedding host added ([`add_model_dir`]).
pub fn model_dirs() -> Vec<PathBuf> {
    if let Some(dir) = std::env::var_os("R2D2_MODELS").filter(|d| !d.is_empty()) {
        return vec![PathBuf::from(dir)];
    }
    let mut dirs = vec![PathBuf::from("models")];
    if let Some(bin) = std::env::current_exe().ok().and_then(|e| e.parent().map(Path::to_path_buf)) {
        dirs.push(bin.join("../../models"));
        dirs.push(bin.join("../share/r2d2-imaging/models"));
    }
    if let Ok(host) = HOST_MODEL_DIRS.read() {
        dirs.extend(host.iter().cloned());
    }
    dirs
}

/// A series given as a directory (any path with a separator, or one that exists) or as a bare
/// name looked up in [`model_dirs`]: in the first that has it, the series of that name (its
/// manifest's `name`, which the log shows), else the directory of that name. A name two series
/// of one directory share is an error naming both.
pub fn resolve(series: &Path) -> Result<PathBuf> {
    resolve_in(&model_dirs(), series)
}

fn resolve_in(dirs: &[PathBuf], series: &Path) -> Result<PathBuf> {
    let bare = series.components().count() == 1 && !series.is_dir();
    if !bare {
        return Ok(series.to_path_buf());
    }
    for root in dirs {
        let opened = open_all(root);
        let named = opened.iter().position(|(_, s)| s.as_ref().is_ok_and(|s| s.name.as_str() == series.as_os_str()));
        if let Some(k) = named {
            if let Some(other) = sharing_the_name(&opened, k) {
                return Err(shared_name_error(&opened[k].0, &series.to_string_lossy(), other));
            }
            return Ok(opened[k].0.clone());
        }
        if root.join(series).is_dir() {
            return Ok(root.join(series));
        }
    }
    let looked: Vec<String> = dirs.iter().map(|d| d.display().to_string()).collect();
    let message = format!("no model series of that name in {} (set R2D2_MODELS, or give the series directory)", looked.join(", "));
    Err(SeriesError::NotFound { name: series.to_path_buf(), message }.into())
}

/// The series directories under `root`, each with its series or why it is none; two whose
/// series share a name are both errors naming the other (a name must pick one series).
pub fn discover(root: &Path) -> Vec<(PathBuf, Result<Series>)> {
    let opened = open_all(root);
    let shared: Vec<Option<PathBuf>> = (0..opened.len()).map(|k| sharing_the_name(&opened, k).map(Path::to_path_buf)).collect();
    opened
        .into_iter()
        .zip(shared)
        .map(|((dir, series), other)| match (series, other) {
            (Ok(series), Some(other)) => {
                let error = shared_name_error(&dir, &series.name, &other);
                (dir, Err(error))
            }
            (series, _) => (dir, series),
        })
        .collect()
}

/// Every directory under `root`, in name order, with its series as read.
fn open_all(root: &Path) -> Vec<(PathBuf, Result<Series>)> {
    let mut dirs: Vec<PathBuf> = match std::fs::read_dir(root) {
        Ok(rd) => rd.filter_map(|e| e.ok()).map(|e| e.path()).filter(|p| p.is_dir()).collect(),
        Err(_) => Vec::new(),
    };
    dirs.sort();
    dirs.into_iter().map(|d| {
        let s = Series::open(&d);
        (d, s)
    }).collect()
}

/// Another directory of `opened` whose series has the name of the `k`th one's.
fn sharing_the_name(opened: &[(PathBuf, Result<Series>)], k: usize) -> Option<&Path> {
    let name = &opened[k].1.as_ref().ok()?.name;
    opened.iter().enumerate().find(|(j, (_, s))| *j != k && s.as_ref().is_ok_and(|s| &s.name == name)).map(|(_, (dir, _))| dir.as_path())
}

fn shared_name_error(dir: &Path, name: &str, other: &Path) -> Error {
    invalid(
        dir,
        format!("series '{name}' has the name of the series in {} too: a name must pick one series (`auto` logs it, the request's `step` takes it); give one of them another `name` in its manifest", other.display()),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn touch(p: &Path) {
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, b"x").unwrap();
    }

    fn series_dir(root: &Path, name: &str, sizes: &str, any_size: bool) {
        let dir = root.join(name);
        touch(&dir.join("a.onnx"));
        let manifest = format!(
            "format: 1\nname: {name}\narchitecture: r2d2\nimage_sizes: {sizes}\nany_size: {any_size}\ninput_convention: reference\nnormalisation: mean\nnetworks: [a.onnx]\n"
        );
        std::fs::write(dir.join("manifest.yaml"), manifest).unwrap();
    }

    /// A series is named by its manifest's `name` (what the log shows), whatever its folder;
    /// two folders of one directory with one name are refused by `auto`, by the name and in the
    /// listing, each naming the other folder. An earlier directory's series still stands
    /// before a later one's of the same name.
    #[test]
    fn a_name_picks_one_series_by_its_manifest_and_a_shared_one_is_refused() {
        let root = tempfile::tempdir().unwrap();
        let roots = [root.path().to_path_buf()];
        series_dir(root.path(), "aaa", "[512]", true);
        series_dir(root.path(), "bbb", "[512]", true);
        let rename = |folder: &str, name: &str| {
            let manifest = root.path().join(folder).join("manifest.yaml");
            let text = std::fs::read_to_string(&manifest).unwrap().replace(&format!("name: {folder}\n"), &format!("name: {name}\n"));
            std::fs::write(&manifest, text).unwrap();
        };
        rename("bbb", "shared");
        assert_eq!(resolve_in(&roots, Path::new("shared")).unwrap(), root.path().join("bbb"));
        assert_eq!(resolve_in(&roots, Path::new("aaa")).unwrap(), root.path().join("aaa"));
        assert_eq!(select_in(&roots, 512, &ImagingSetup::default()).unwrap().0, root.path().join("aaa"));
        rename("aaa", "shared");
        let both = |e: String| {
            for folder in ["aaa", "bbb"] {
                assert!(e.contains(&root.path().join(folder).display().to_string()), "{folder} missing from: {e}");
            }
            assert!(e.contains("series 'shared'") && e.contains("a name must pick one series"), "{e}");
        };
        both(select_in(&roots, 512, &ImagingSetup::default()).unwrap_err().to_string());
        both(resolve_in(&roots, Path::new("shared")).unwrap_err().to_string());
        for (_, series) in discover(root.path()) {
            both(series.unwrap_err().to_string());
        }
        // In two directories, the earlier one's series of the name stands.
        let later = tempfile::tempdir().unwrap();
        series_dir(later.path(), "vla-r2d2-512", "[512]", true);
        series_dir(root.path(), "vla-r2d2-512", "[512]", true);
        std::fs::remove_dir_all(root.path().join("aaa")).unwrap();
        let roots = [root.path().to_path_buf(), later.path().to_path_buf()];
        assert_eq!(resolve_in(&roots, Path::new("vla-r2d2-512")).unwrap(), root.path().join("vla-r2d2-512"));
        assert_eq!(ranked_series(&roots).unwrap().iter().filter(|(_, s)| s.name == "vla-r2d2-512").count(), 1);
    }

    /// NaN or reversed validity ranges are refused when the manifest is read, naming the key.
    #[test]
    fn validity_ranges_must_be_finite_and_ordered() {
        let root = tempfile::tempdir().unwrap();
        series_dir(root.path(), "s", "[512]", true);
        let dir = root.path().join("s");
        let manifest = dir.join("manifest.yaml");
        let text = std::fs::read_to_string(&manifest).unwrap();
        for (bad, key) in [("superresolution: [.nan, .nan]", "validity.superresolution"), ("robust: [1.0, -1.0]", "validity.robust"), ("track_hours: [.inf, 8.0]", "validity.track_hours")] {
            std::fs::write(&manifest, format!("{text}validity: {{{bad}}}\n")).unwrap();
            let e = Series::open(&dir).err().expect("refused").to_string();
            assert!(e.contains(key) && e.contains("finite"), "{bad}: {e}");
        }
        std::fs::write(&manifest, format!("{text}validity: {{superresolution: [1.5, 2.0], robust: [-1.0, 0.0]}}\n")).unwrap();
        assert!(Series::open(&dir).is_ok());
    }

    /// A series' own emission-mask level is read; zero, negative or not a number is refused,
    /// naming the key.
    #[test]
    fn a_series_auto_mask_is_read_and_must_be_a_positive_number() {
        let root = tempfile::tempdir().unwrap();
        series_dir(root.path(), "s", "[512]", true);
        let dir = root.path().join("s");
        assert_eq!(Series::open(&dir).unwrap().auto_mask, None);
        let manifest = dir.join("manifest.yaml");
        let text = std::fs::read_to_string(&manifest).unwrap();
        std::fs::write(&manifest, format!("{text}auto_mask: 5\n")).unwrap();
        assert_eq!(Series::open(&dir).unwrap().auto_mask, Some(5.0));
        for bad in ["0", "-1", ".nan", ".inf"] {
            std::fs::write(&manifest, format!("{text}auto_mask: {bad}\n")).unwrap();
            let e = Series::open(&dir).err().expect("refused").to_string();
            assert!(e.contains("auto_mask") && e.contains("positive"), "{bad}: {e}");
        }
    }

    #[test]
    fn early_stop_from_is_read_and_must_name_a_network_of_the_series() {
        let root = tempfile::tempdir().unwrap();
        series_dir(root.path(), "plain", "[512]", true);
        assert_eq!(Series::open(&root.path().join("plain")).unwrap().early_stop_from, 1);
        let dir = root.path().join("staged");
        touch(&dir.join("a.onnx"));
        touch(&dir.join("b.onnx"));
        let manifest = |from: usize| format!(
            "format: 1\nname: staged\narchitecture: r2d2\nimage_sizes: [512]\ninput_convention: reference\nnormalisation: mean\nnetworks: [a.onnx, b.onnx]\nearly_stop_from: {from}\n"
        );
        std::fs::write(dir.join("manifest.yaml"), manifest(2)).unwrap();
        assert_eq!(Series::open(&dir).unwrap().early_stop_from, 2);
        for from in [0, 3] {
            std::fs::write(dir.join("manifest.yaml"), manifest(from)).unwrap();
            let e = Series::open(&dir).err().expect("refused").to_string();
            assert!(e.contains("manifest.yaml") && e.contains("early_stop_from: expected a network of the series, 1 to 2"), "{e}");
        }
    }

    #[test]
    fn the_nearest_trained_size_is_by_ratio_the_larger_of_two_as_near() {
        let root = tempfile::tempdir().unwrap();
        series_dir(root.path(), "two", "[128, 512]", true);
        let series = Series::open(&root.path().join("two")).unwrap();
        let nearest = |size| series.nearest_trained_size(size).unwrap();
        assert_eq!((nearest(128), nearest(200), nearest(256), nearest(300), nearest(2048)), (128, 128, 512, 512, 512));
    }

    /// A size a series' domain names without its being trained there (measured on held-out
    /// data) makes it a choice there as at a trained size, by rank, without the off-size
    /// warning; its trained size still rules what off-size imaging needs (the weighting grid).
    #[test]
    fn a_size_the_domain_names_serves_as_a_trained_one() {
        let root = tempfile::tempdir().unwrap();
        let roots = [root.path().to_path_buf()];
        series_dir(root.path(), "vla-r2d2-512", "[512]", true);
        series_dir(root.path(), "vla-r2d2-128", "[128]", true);
        let pick = |size| select_in(&roots, size, &ImagingSetup::default()).unwrap();
        assert_eq!(pick(128), (root.path().join("vla-r2d2-128"), None));
        let manifest = root.path().join("vla-r2d2-512/manifest.yaml");
        let text = std::fs::read_to_string(&manifest).unwrap();
        std::fs::write(&manifest, format!("{text}validity: {{image_sizes: [128, 512]}}\n")).unwrap();
        assert_eq!(pick(128), (root.path().join("vla-r2d2-512"), None));
        assert_eq!(pick(512).0, root.path().join("vla-r2d2-512"));
        let series = Series::open(&root.path().join("vla-r2d2-512")).unwrap();
        assert!(series.serves_size(128) && series.serves_size(512) && !series.serves_size(256));
        assert_eq!(series.check_size(128).unwrap(), None, "no off-size warning where the domain names the size");
        assert!(series.check_size(256).unwrap().is_some());
        assert_eq!(series.nearest_trained_size(128), Some(512), "off-size handling goes by the trained size");
        // Not of the job's setting there: the series trained at the size, as before.
        std::fs::write(&manifest, format!("{text}validity: {{image_sizes: [128, 512], robust: [0.0, 0.0]}}\n")).unwrap();
        let briggs1 = ImagingSetup { weighting: Some("briggs".into()), robust: Some(1.0), ..ImagingSetup::default() };
        let v128 = root.path().join("vla-r2d2-128/manifest.yaml");
        let t128 = std::fs::read_to_string(&v128).unwrap();
        std::fs::write(&v128, format!("{t128}validity: {{robust: [0.0, 0.0]}}\n")).unwrap();
        assert_eq!(select_in(&roots, 128, &briggs1).unwrap().0, root.path().join("vla-r2d2-512"), "neither holds it, as near: the rank");
        std::fs::write(&v128, format!("{t128}validity: {{robust: [-1.0, 1.0]}}\n")).unwrap();
        assert_eq!(select_in(&roots, 128, &briggs1).unwrap().0, root.path().join("vla-r2d2-128"), "the one whose domain holds the setting");
        // The data's telescope counts before the size: MeerKAT data at a size only a VLA series
        // serves go to the MeerKAT series, off its trained size, with the warning.
        std::fs::write(&manifest, format!("{text}validity: {{image_sizes: [128, 512], telescopes: [vla]}}\n")).unwrap();
        std::fs::write(&v128, format!("{t128}validity: {{telescopes: [vla]}}\n")).unwrap();
        let meerkat = ImagingSetup { telescope: Some("MeerKAT".into()), ..ImagingSetup::default() };
        assert_eq!(select_in(&roots, 128, &meerkat).unwrap().0, root.path().join("vla-r2d2-512"), "none of the telescope: the size's");
        series_dir(root.path(), "meerkat-r2d2-512", "[512]", true);
        std::fs::write(root.path().join("meerkat-r2d2-512/manifest.yaml"), format!("{}validity: {{telescopes: [meerkat]}}\n", std::fs::read_to_string(root.path().join("meerkat-r2d2-512/manifest.yaml")).unwrap())).unwrap();
        let (dir, warning) = select_in(&roots, 128, &meerkat).unwrap();
        assert_eq!(dir, root.path().join("meerkat-r2d2-512"));
        assert!(warning.is_some_and(|w| w.contains("no series was trained for 128 x 128")));
        assert_eq!(select_in(&roots, 128, &ImagingSetup { telescope: Some("VLA".into()), ..ImagingSetup::default() }).unwrap().0, root.path().join("vla-r2d2-512"));
        // A series that declares no telescope is not one trained for MeerKAT's: the size's
        // series stands before it.
        std::fs::remove_dir_all(root.path().join("meerkat-r2d2-512")).unwrap();
        series_dir(root.path(), "zzz-any-2048", "[2048]", true);
        assert_eq!(select_in(&roots, 128, &meerkat).unwrap().0, root.path().join("vla-r2d2-512"));
    }

    #[test]
    fn auto_picks_the_series_trained_for_the_size_then_the_nearest_with_a_warning() {
        let root = tempfile::tempdir().unwrap();
        let roots = [root.path().to_path_buf()];
        series_dir(root.path(), "aaa-other-512", "[512]", true);
        series_dir(root.path(), "vla-r2d2-512", "[512]", true);
        series_dir(root.path(), "vla-r2d2-128", "[128]", true);
        series_dir(root.path(), "fixed-64", "[64]", false);
        let pick = |size| select_in(&roots, size, &ImagingSetup::default()).unwrap();
        // Trained for the size: the project's own series before others of the same size.
        assert_eq!(pick(512), (root.path().join("vla-r2d2-512"), None));
        assert_eq!(pick(128), (root.path().join("vla-r2d2-128"), None));
        // Only allowed for other sizes: trained for 64, fixed -- chosen at 64, never elsewhere.
        assert_eq!(pick(64), (root.path().join("fixed-64"), None));
        // No series for the size: the nearest trained size that allows others, with a warning.
        let (dir, warning) = pick(256);
        assert!(dir == root.path().join("vla-r2d2-512") || dir == root.path().join("vla-r2d2-128"), "{dir:?}");
        let (dir, warning96) = pick(96);
        assert_eq!(dir, root.path().join("vla-r2d2-128"));
        assert!(warning96.unwrap().contains("no series was trained for 96 x 96"));
        assert!(warning.unwrap().contains("256 x 256"));
        assert_eq!(pick(2048).0, root.path().join("vla-r2d2-512"));
        // Equally near: one whose domain holds the setting, then the rank.
        series_dir(root.path(), "vla-r2d2-512-broad", "[512]", true);
        let broad = root.path().join("vla-r2d2-512-broad/manifest.yaml");
        let text = std::fs::read_to_string(&broad).unwrap();
        std::fs::write(&broad, format!("{text}validity: {{superresolution: [1.5, 2.5], robust: [-1.0, 1.0]}}\n")).unwrap();
        let narrow = root.path().join("vla-r2d2-512/manifest.yaml");
        let text = std::fs::read_to_string(&narrow).unwrap();
        std::fs::write(&narrow, format!("{text}validity: {{superresolution: [1.5, 2.0], robust: [-1.0, 0.0]}}\n")).unwrap();
        assert_eq!(pick(2048).0, root.path().join("vla-r2d2-512"));
        assert_eq!(pick(1024).0, root.path().join("vla-r2d2-512"));
        let briggs1 = ImagingSetup { weighting: Some("briggs".into()), robust: Some(1.0), ..ImagingSetup::default() };
        assert_eq!(select_in(&roots, 1024, &briggs1).unwrap().0, root.path().join("vla-r2d2-512-broad"));
        // At its size the project's order stands.
        assert_eq!(pick(512).0, root.path().join("vla-r2d2-512"));
        // A setting outside every domain at the size: the domain nearest to it, not the first
        // ranked (Briggs 1.5 is 0.5 beyond the broad -1..1, 1.5 beyond the narrow -1..0). A
        // series that declares no domain holds every setting: without it here.
        std::fs::remove_dir_all(root.path().join("aaa-other-512")).unwrap();
        let briggs = |robust| ImagingSetup { weighting: Some("briggs".into()), robust: Some(robust), ..ImagingSetup::default() };
        assert_eq!(select_in(&roots, 512, &briggs(1.5)).unwrap().0, root.path().join("vla-r2d2-512-broad"));
        assert_eq!(select_in(&roots, 512, &briggs(-2.0)).unwrap().0, root.path().join("vla-r2d2-512"), "equally near: the rank");
        let sr = |sr| ImagingSetup { superresolution: Some(sr), ..ImagingSetup::default() };
        assert_eq!(select_in(&roots, 512, &sr(3.0)).unwrap().0, root.path().join("vla-r2d2-512-broad"));
        assert_eq!(select_in(&roots, 512, &sr(1.2)).unwrap().0, root.path().join("vla-r2d2-512"), "equally near: the rank");
        // A setting only the narrower domain holds: it goes first off-size too.
        let sr3 = ImagingSetup { superresolution: Some(3.0), ..ImagingSetup::default() };
        let narrow3 = std::fs::read_to_string(&narrow).unwrap().replace("[1.5, 2.0]", "[1.5, 3.0]");
        std::fs::write(&narrow, narrow3).unwrap();
        assert_eq!(select_in(&roots, 1024, &sr3).unwrap().0, root.path().join("vla-r2d2-512"));
        // Nothing usable: an error naming where it looked.
        let empty = tempfile::tempdir().unwrap();
        let e = select_in(&[empty.path().to_path_buf()], 512, &ImagingSetup::default()).unwrap_err().to_string();
        assert!(e.contains("no model series for 512 x 512") && e.contains(&empty.path().display().to_string()), "{e}");
    }

    #[test]
    fn auto_prefers_the_datas_telescope_at_the_size_and_off_it() {
        let root = tempfile::tempdir().unwrap();
        let roots = [root.path().to_path_buf()];
        for (name, telescope) in [("vla-r2d2-512", "vla"), ("meerkat-r2d2-512", "meerkat")] {
            series_dir(root.path(), name, "[512]", true);
            let manifest = root.path().join(name).join("manifest.yaml");
            let text = std::fs::read_to_string(&manifest).unwrap();
            std::fs::write(&manifest, format!("{text}validity: {{telescopes: [{telescope}]}}\n")).unwrap();
        }
        let pick = |size, telescope: &str| {
            let setup = ImagingSetup { telescope: Some(telescope.to_string()), ..ImagingSetup::default() };
            select_in(&roots, size, &setup).unwrap().0
        };
        assert_eq!(pick(512, "VLA"), root.path().join("vla-r2d2-512"));
        assert_eq!(pick(512, "MeerKAT"), root.path().join("meerkat-r2d2-512"));
        // Off the trained size the telescope still counts before the project's order.
        assert_eq!(pick(256, "MeerKAT"), root.path().join("meerkat-r2d2-512"));
        assert_eq!(pick(256, "VLA"), root.path().join("vla-r2d2-512"));
        // Data naming no telescope keep the project's order.
        assert_eq!(pick(512, "unknown"), root.path().join("vla-r2d2-512"));
    }

    #[test]
    fn orientations_turn_the_grid_as_documented_and_back() {
        use Orientation::*;
        // f = [[0, 1, 2], [3, 4, 5], [6, 7, 8]] turned, written out by hand.
        let f: Vec<u8> = (0..9).collect();
        let expected: [(Orientation, [u8; 9]); 8] = [
            (Identity, [0, 1, 2, 3, 4, 5, 6, 7, 8]),
            (MirrorX, [2, 1, 0, 5, 4, 3, 8, 7, 6]),
            (MirrorY, [6, 7, 8, 3, 4, 5, 0, 1, 2]),
            (Rotate180, [8, 7, 6, 5, 4, 3, 2, 1, 0]),
            (Transpose, [0, 3, 6, 1, 4, 7, 2, 5, 8]),
            (Rotate90, [2, 5, 8, 1, 4, 7, 0, 3, 6]),
            (Rotate270, [6, 3, 0, 7, 4, 1, 8, 5, 2]),
            (AntiTranspose, [8, 5, 2, 7, 4, 1, 6, 3, 0]),
        ];
        for (o, want) in expected {
            assert_eq!(o.apply(f.clone(), 3), want, "{o:?}");
            // A stack (a network's two input channels): each image turned on its own.
            assert_eq!(o.apply([f.clone(), f.clone()].concat(), 3), [want, want].concat(), "{o:?} on a stack");
        }
        // Each is undone by its inverse, on an even size too; the eight are distinct.
        let g: Vec<u16> = (0..16).collect();
        let turned: Vec<Vec<u16>> = expected.iter().map(|(o, _)| o.apply(g.clone(), 4)).collect();
        for ((o, _), t) in expected.iter().zip(&turned) {
            assert_eq!(o.inverse().apply(t.clone(), 4), g, "{o:?}");
        }
        for (i, a) in turned.iter().enumerate() {
            assert!(turned[i + 1..].iter().all(|b| b != a), "orientation {i} repeats another");
        }
    }

    #[test]
    fn an_orientation_cycle_is_read_by_name_and_only_for_r2d2() {
        let dir = tempfile::tempdir().unwrap();
        touch(&dir.path().join("a.onnx"));
        let base = "format: 1\nname: t\narchitecture: r2d2\nimage_sizes: [64]\ninput_convention: reference\nnormalisation: mean\nnetworks: [a.onnx]\n";
        let write = |extra: &str| std::fs::write(dir.path().join("manifest.yaml"), format!("{base}{extra}")).unwrap();
        write("orientation_cycle: [identity, mirror_x, rotate_90, anti_transpose]\n");
        let s = Series::open(dir.path()).unwrap();
        assert_eq!(s.orientation_cycle, [Orientation::Identity, Orientation::MirrorX, Orientation::Rotate90, Orientation::AntiTranspose]);
        write("");
        assert!(Series::open(dir.path()).unwrap().orientation_cycle.is_empty(), "none: every network as trained");
        write("orientation_cycle: [identity, flip]\n");
        let e = Series::open(dir.path()).err().expect("unknown orientation refused").to_string();
        assert!(e.contains("orientation_cycle") && e.contains("flip") && e.contains("rotate_90"), "{e}");
        let r3d3 = base.replace("architecture: r2d2", "architecture: r3d3\nlayers: 1");
        std::fs::write(dir.path().join("manifest.yaml"), format!("{r3d3}orientation_cycle: [identity, mirror_x]\n")).unwrap();
        let e = Series::open(dir.path()).err().expect("R3D3 with a cycle refused").to_string();
        assert!(e.contains("orientation_cycle") && e.contains("R2D2"), "{e}");
    }

    #[test]
    fn reference_r2d2_names_are_inferred_in_order() {
        let dir = tempfile::tempdir().unwrap();
        for i in [2, 1, 10, 3, 4, 5, 6, 7, 8, 9] {
            touch(&dir.path().join(format!("R2D2_UNet_N{i}.onnx")));
        }
        let s = Series::open(dir.path()).unwrap();
        assert_eq!(s.architecture, Architecture::R2d2);
        assert_eq!(s.len(), 10);
        assert!(s.files[9][0].ends_with("R2D2_UNet_N10.onnx"));
        assert!(s.any_size && s.manifest.is_none());
        assert!(s.check_size(512).unwrap().is_some(), "running without a manifest warns");
    }

    #[test]
    fn reference_r3d3_names_are_inferred_with_layers() {
        let dir = tempfile::tempdir().unwrap();
        for i in 1..=2 {
            for l in 1..=3 {
                touch(&dir.path().join(format!("R3D3_R2D2Net_3Layers_N{i}/R3D3_R2D2Net_3Layers_N{i}_L{l}.onnx")));
            }
        }
        let s = Series::open(dir.path()).unwrap();
        assert_eq!((s.architecture, s.len(), s.layers()), (Architecture::R3d3, 2, 3));
        assert!(s.files[1][2].ends_with("R3D3_R2D2Net_3Layers_N2/R3D3_R2D2Net_3Layers_N2_L3.onnx"));
    }

    #[test]
    fn gaps_and_missing_files_are_errors_naming_them() {
        let dir = tempfile::tempdir().unwrap();
        touch(&dir.path().join("R2D2_UNet_N1.onnx"));
        touch(&dir.path().join("R2D2_UNet_N3.onnx"));
        let e = Series::open(dir.path()).unwrap_err().to_string();
        assert!(e.contains("without gaps") && e.contains("[1, 3]"), "{e}");

        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("manifest.yaml"),
            "format: 1\nname: t\narchitecture: r2d2\nimage_sizes: [64]\ninput_convention: reference\nnormalisation: mean\nnetworks: [a.onnx]\n",
        )
        .unwrap();
        let err = Series::open(dir.path()).unwrap_err();
        let e = err.to_string();
        assert!(e.contains("a.onnx") && e.contains("missing"), "{e}");
        // The kind, and the system's error beneath it.
        let Error::Series(SeriesError::MissingNetwork { path, series, .. }) = &err else { panic!("{err:?}") };
        assert_eq!((path.as_path(), series.as_str()), (dir.path().join("a.onnx").as_path(), "t"));
        let module = std::error::Error::source(&err).expect("the series error");
        let io = module.source().and_then(|c| c.downcast_ref::<std::io::Error>()).expect("the system's error");
        assert_eq!(io.kind(), std::io::ErrorKind::NotFound);
        assert_eq!(e.matches(&io.to_string()).count(), 1, "{e}");
    }

    /// A FIFO or a directory where a network or the manifest should be is said to be one, and
    /// never opened (a FIFO's open would block until a writer came).
    #[cfg(unix)]
    #[test]
    fn fifos_and_directories_are_not_network_files() {
        let mkfifo = |path: &Path| assert!(std::process::Command::new("mkfifo").arg(path).status().unwrap().success());
        let dir = tempfile::tempdir().unwrap();
        touch(&dir.path().join("R2D2_UNet_N1.onnx"));
        mkfifo(&dir.path().join("R2D2_UNet_N2.onnx"));
        std::fs::create_dir(dir.path().join("R2D2_UNet_N3.onnx")).unwrap();
        let e = Series::open(dir.path()).unwrap_err().to_string();
        assert!(e.contains("R2D2_UNet_N2.onnx") && e.contains("is a FIFO (named pipe), not a regular file") && !e.contains("missing"), "{e}");
        std::fs::remove_file(dir.path().join("R2D2_UNet_N2.onnx")).unwrap();
        touch(&dir.path().join("R2D2_UNet_N2.onnx"));
        let e = Series::open(dir.path()).unwrap_err().to_string();
        assert!(e.contains("R2D2_UNet_N3.onnx") && e.contains("is a directory, not a regular file") && !e.contains("missing"), "{e}");
        mkfifo(&dir.path().join("manifest.yaml"));
        let e = Series::open(dir.path()).unwrap_err().to_string();
        assert!(e.contains("manifest.yaml") && e.contains("the manifest is a FIFO (named pipe)"), "{e}");
    }

    /// A series `dir/s` whose manifest lists `networks`.
    fn series_listing(dir: &Path, networks: &str) -> PathBuf {
        let series = dir.join("s");
        std::fs::create_dir_all(&series).unwrap();
        let manifest = format!("format: 1\nname: t\narchitecture: r2d2\nimage_sizes: [64]\ninput_convention: reference\nnormalisation: mean\nnetworks: {networks}\n");
        std::fs::write(series.join("manifest.yaml"), manifest).unwrap();
        series
    }

    #[test]
    fn network_entries_must_resolve_inside_the_series_directory() {
        let dir = tempfile::tempdir().unwrap();
        touch(&dir.path().join("outside.onnx"));
        for entry in ["../outside.onnx", "/etc/passwd", "sub/../../outside.onnx"] {
            let series = series_listing(dir.path(), &format!("[\"{entry}\"]"));
            let e = Series::open(&series).err().map(|e| e.to_string()).unwrap_or_else(|| panic!("{entry} accepted"));
            assert!(e.contains("networks[0]") && e.contains(entry) && e.contains("inside the series directory"), "{e}");
        }
        // A link inside that points outside is found out through the canonical path.
        let series = series_listing(dir.path(), "[link.onnx]");
        std::os::unix::fs::symlink(dir.path().join("outside.onnx"), series.join("link.onnx")).unwrap();
        let e = Series::open(&series).err().map(|e| e.to_string()).expect("a link to outside accepted");
        assert!(e.contains("link.onnx") && e.contains("outside the series directory"), "{e}");
    }

    #[test]
    fn empty_network_files_make_a_series_unusable() {
        let dir = tempfile::tempdir().unwrap();
        let series = series_listing(dir.path(), "[a.onnx]");
        std::fs::write(series.join("a.onnx"), b"").unwrap();
        let found = discover(dir.path());
        assert_eq!(found.len(), 1);
        let e = found[0].1.as_ref().err().map(|e| e.to_string()).expect("a 0-byte network listed as usable");
        assert!(e.contains("a.onnx") && e.contains("empty"), "{e}");
    }

    #[test]
    fn realisations_are_listed_in_order_and_must_agree_in_length() {
        let dir = tempfile::tempdir().unwrap();
        for f in ["V1/a.onnx", "V1/b.onnx", "V2/a.onnx", "V2/b.onnx"] {
            touch(&dir.path().join(f));
        }
        let base = "format: 1\nname: t\narchitecture: r2d2\nimage_sizes: [64]\ninput_convention: reference\nnormalisation: mean\n";
        let write = |rest: &str| std::fs::write(dir.path().join("manifest.yaml"), format!("{base}{rest}")).unwrap();
        write("realisations: [[V1/a.onnx, V1/b.onnx], [V2/a.onnx, V2/b.onnx]]\n");
        let s = Series::open(dir.path()).unwrap();
        assert_eq!((s.len(), s.realisations), (2, 2));
        assert!(s.realisation(1)[0][0].ends_with("V2/a.onnx") && s.realisation(0)[1][0].ends_with("V1/b.onnx"));
        write("realisations: [[V1/a.onnx, V1/b.onnx], [V2/a.onnx]]\n");
        let e = Series::open(dir.path()).unwrap_err().to_string();
        assert!(e.contains("realisations[1]") && e.contains("expected 2 networks"), "{e}");
        write("networks: [V1/a.onnx]\nrealisations: [[V2/a.onnx]]\n");
        let e = Series::open(dir.path()).unwrap_err().to_string();
        assert!(e.contains("give one of them"), "{e}");
        write("realisations: [[V1/a.onnx], [\"../x.onnx\"]]\n");
        let e = Series::open(dir.path()).unwrap_err().to_string();
        assert!(e.contains("realisations[1][0]") && e.contains("inside the series directory"), "{e}");
    }

    /// A one-network series in `dir` whose manifest declares `validity` (a YAML mapping).
    fn series_with_validity(dir: &Path, validity: &str) -> Series {
        touch(&dir.join("a.onnx"));
        let manifest = format!("format: 1\nname: t\narchitecture: r2d2\nimage_sizes: [64]\ninput_convention: reference\nnormalisation: mean\nnetworks: [a.onnx]\nvalidity: {validity}\n");
        std::fs::write(dir.join("manifest.yaml"), manifest).unwrap();
        Series::open(dir).unwrap()
    }

    #[test]
    fn validity_ranges_report_each_problem() {
        let dir = tempfile::tempdir().unwrap();
        let s = series_with_validity(dir.path(), "{telescopes: [vla], superresolution: [1.5, 2.5], robust: [-1, 1], weighting: [briggs]}");
        let setup = |sr, scheme: &str, robust| ImagingSetup { superresolution: sr, weighting: Some(scheme.to_string()), robust: Some(robust), ..ImagingSetup::default() };
        assert!(s.validity_problems(&setup(Some(2.5), "briggs", -1.0)).is_empty());
        // Within the tolerance of the SR range; CASA's name of the VLA is the VLA.
        assert!(s.validity_problems(&ImagingSetup { telescope: Some("EVLA".into()), ..setup(Some(2.6), "briggs", 0.0) }).is_empty());
        let p = s.validity_problems(&ImagingSetup { telescope: Some("MeerKAT".into()), ..setup(Some(1.45), "briggs", 0.0) });
        assert_eq!(p.len(), 1, "{p:?}");
        assert!(p[0].contains("'MeerKAT'") && p[0].contains("vla"), "{p:?}");
        let p = s.validity_problems(&setup(Some(3.0), "briggs", 1.5));
        assert_eq!(p.len(), 2, "{p:?}");
        assert!(p[0].contains("super-resolution 3") && p[1].contains("robust 1.5"), "{p:?}");
        let p = s.validity_problems(&setup(None, "natural", 5.0));
        assert_eq!(p.len(), 1, "robust is not checked for natural weighting, SR unknown is not checked: {p:?}");
        assert!(p[0].contains("weighting 'natural'"), "{p:?}");
    }

    #[test]
    fn a_track_or_integration_outside_the_trained_ones_is_a_problem() {
        let dir = tempfile::tempdir().unwrap();
        let s = series_with_validity(dir.path(), "{telescopes: [meerkat], track_hours: [8, 12], integration_s: [60, 60]}");
        let setup = |hours, seconds| ImagingSetup { track_hours: hours, integration_s: seconds, ..ImagingSetup::default() };
        assert!(s.validity_problems(&setup(Some(10.0), Some(60.0))).is_empty());
        // Within the tolerances; data without times are not checked.
        assert!(s.validity_problems(&setup(Some(7.5), Some(62.0))).is_empty());
        assert!(s.validity_problems(&setup(None, None)).is_empty());
        // A shorter integration samples the same tracks more densely: not a problem.
        assert!(s.validity_problems(&setup(Some(10.0), Some(8.0))).is_empty());
        let p = s.validity_problems(&setup(Some(4.0), Some(120.0)));
        assert_eq!(p.len(), 2, "{p:?}");
        assert!(p[0].contains("a track of 4.0 h") && p[0].contains("range 8..12 h"), "{p:?}");
        assert!(p[1].contains("integration time of 120 s is longer") && p[1].contains("setting 60 s"), "{p:?}");
        assert!(s.validity_problems(&setup(Some(13.5), None))[0].contains("a track of 13.5 h"));
        // Measured distances: a track nearer the range is nearer the domain, and less far than a
        // problem no distance measures.
        assert!(s.domain_distance(&setup(Some(6.0), None)) < s.domain_distance(&setup(Some(2.0), None)));
        assert!(s.domain_distance(&setup(Some(2.0), Some(1.0))) < 100.0);
    }

    #[test]
    fn manifest_errors_name_the_key_and_line() {
        let dir = tempfile::tempdir().unwrap();
        touch(&dir.path().join("a.onnx"));
        let base = "name: t\narchitecture: r2d2\nimage_sizes: [64]\ninput_convention: reference\nnormalisation: mean\nnetworks: [a.onnx]\n";
        std::fs::write(dir.path().join("manifest.yaml"), format!("format: 2\n{base}")).unwrap();
        let e = Series::open(dir.path()).unwrap_err().to_string();
        assert!(e.contains("manifest.yaml") && e.contains("format 1") && e.contains("got 2"), "{e}");

        std::fs::write(dir.path().join("manifest.yaml"), format!("format: 1\n{base}colour: red\n")).unwrap();
        let err = Series::open(dir.path()).unwrap_err();
        let e = err.to_string();
        assert!(e.contains("colour") && e.contains("line 8"), "{e}");
        let Error::Series(SeriesError::Manifest { source, .. }) = &err else { panic!("{err:?}") };
        assert_eq!(e.matches(&source.to_string()).count(), 1, "the parser's words once: {e}");

        std::fs::write(dir.path().join("manifest.yaml"), format!("format: 1\n{base}any_size: false\n")).unwrap();
        let s = Series::open(dir.path()).unwrap();
        assert!(s.check_size(64).unwrap().is_none());
        let e = s.check_size(128).unwrap_err().to_string();
        assert!(e.contains("[64]") && e.contains("128 x 128"), "{e}");
    }
}
