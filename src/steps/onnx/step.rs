//! The ONNX series step itself (see the module above for how it runs a series).


use crate::steps::{JobDomain, NetworkStep, StepInput};
use crate::deconv::{main_lobe_fwhm_px, EmissionMask, DEFAULT_AUTO_MASK};
use super::check::{check_network, Signature};
use super::runtime::{BackendChoice, GraphOptimization, Network, Runtime};
use super::series::{Architecture, ImagingSetup, Series};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct OnnxConfig {
    /// Series directory (`models/<name>`: a manifest and ONNX files, or the reference names),
    /// or a bare series name looked up in the model directories (`super::series::model_dirs`).
    pub series: PathBuf,
    /// `auto` (native ONNX Runtime if found, else tract), `ort` or `tract`.
    #[serde(default)]
    pub backend: BackendChoice,
    /// Intra-op threads for ONNX Runtime (0: the pipeline's `threads`).
    #[serde(default)]
    pub threads: usize,
    /// Run only the first networks of the series.
    #[serde(default)]
    pub networks: Option<usize>,
    /// Load the next network while the current one runs (hides loading; on ONNX Runtime, whose
    /// weights are mapped from the file, a 31 M-parameter network loads in about 0.04 s and
    /// costs about 20 MB until it runs).
    #[serde(default = "yes")]
    pub prefetch: bool,
    /// ONNX Runtime's graph optimisation: `auto` (by the network's size), `extended` (least
    /// memory) or `all` (faster inference, more memory); see `super::runtime::GraphOptimization`.
    #[serde(default)]
    pub graph_optimization: GraphOptimization,
    /// A series of several realisations: run only this one (1-based) instead of all of them.
    #[serde(default)]
    pub realisation: Option<usize>,
    /// A job outside the manifest's `validity` (super-resolution, weighting, robust): `warn`
    /// (the default) or `error`.
    #[serde(default)]
    pub validity: ValidityMode,
    /// A FITS image on the image's grid: after each network the model is kept to where it is
    /// not zero (the step stage reads it and checks it against each job's grid).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fits_mask: Option<PathBuf>,
    /// Keep the model to where the data show emission, found as the series runs: the pixels
    /// where the residual, smoothed to the beam or wider, has risen above this many of its
    /// robust standard deviations (`crate::deconv::EmissionMask`; WSClean's `-auto-mask` for
    /// CLEAN). Unset: 5 on an image more than twice every trained size across, else none; 0:
    /// none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub auto_mask: Option<f64>,
    /// An image larger than every size the series was trained at: `on` runs each network in
    /// overlapping tiles of the largest trained size, blended (memory bounded by the tile);
    /// `off` on the whole image at once; `auto` (the default) tiles an image more than twice
    /// the trained size across and runs a smaller one whole (faster, the same image).
    #[serde(default)]
    pub tiles: TileMode,
}

impl OnnxConfig {
    /// `auto_mask` as given (0: no mask, not even the default one), or an error.
    pub fn given_auto_mask(&self) -> Result<Option<f64>> {
        match self.auto_mask {
            Some(s) if !(s >= 0.0 && s.is_finite()) => Err(Error::parameter("auto_mask", format!("expected a positive number of noise sigmas (or 0: no mask), got {s}"))),
            given => Ok(given),
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum TileMode {
    #[default]
    Auto,
    On,
    Off,
}

/// Tiles share 1 / TILE_OVERLAP_FRACTION of their edge with each neighbour: wide enough that
/// the part of a tile its network saw near a mirrored edge is weighted down to nothing.
const TILE_OVERLAP_FRACTION: usize = 4;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ValidityMode {
    #[default]
    Warn,
    Error,
}

fn yes() -> bool {
    true
}

/// Networks resident at once.
const RESIDENT: usize = 2;

pub struct OnnxStep {
    series: Series,
    runtime: Runtime,
    size: usize,
    /// The series' `edge_padding`: networks run on `size + 2 pad` images.
    pad: usize,
    /// Network steps in all: `per_realisation` times the realisations run.
    iterations: usize,
    per_realisation: usize,
    /// The files of every step, `[iteration - 1][layer]`, realisations one after the other.
    plan: Vec<Vec<PathBuf>>,
    /// Loaded networks, most recently used last, keyed by (iteration, layer).
    resident: Vec<((usize, usize), Box<dyn Network>)>,
    /// The checked signature of every network, `[iteration - 1][layer]`.
    signatures: Vec<Vec<Signature>>,
    prefetch: bool,
    /// Set once calls show several jobs going through the series interleaved.
    interleaved: bool,
    /// The next network, loading on a background thread (counts as resident).
    pending: Option<(Key, std::thread::JoinHandle<Result<Box<dyn Network>>>)>,
    /// The job of the previous call, and the jobs part-way through the series: a job coming
    /// back after another one's call means jobs interleave.
    last_job: Option<String>,
    walking: std::collections::HashSet<String>,
    /// The imaging the pipeline fixes (weighting), completed per job for the domain check.
    setup: ImagingSetup,
    validity: ValidityMode,
    /// The series runs at a size it was not trained for.
    size_warning: Option<String>,
    /// The networks run in tiles of a trained size (an image larger than every one).
    tiling: Option<super::tiles::Tiling>,
    /// The level of the emission mask each job's model is kept to: the config's, or by default
    /// on an image more than twice every trained size across; one mask per job, growing.
    auto_mask: Option<f64>,
    emission: std::collections::HashMap<String, EmissionMask>,
}

type Key = (usize, usize);

impl OnnxStep {
    /// Open and check the series for `size x size` images: every file is read and its input and
    /// output checked here, before imaging starts.
    pub fn new(config: &OnnxConfig, size: usize, pipeline_threads: usize, setup: &ImagingSetup) -> Result<OnnxStep> {
        let series = Series::open(&super::series::resolve_for(&config.series, size, setup)?)?;
        let largest = series.image_sizes.iter().copied().max().filter(|&t| t < size);
        // Tiles and the whole image give the same image (the networks are convolutional; see
        // `tiles.rs`): tiles bound the networks' memory by the tile, the whole image is faster
        // where there are few tiles (a 1024 image takes nine overlapping 512 tiles).
        let tile_edge = match config.tiles {
            TileMode::Off => None,
            TileMode::On => largest,
            TileMode::Auto => largest.filter(|&t| size > 2 * t),
        };
        let tiling = match tile_edge {
            Some(t) if series.architecture == Architecture::R2d2 && series.check_size(t)?.is_none() => super::tiles::Tiling::new(size, t, t / TILE_OVERLAP_FRACTION),
            _ => None,
        };
        // A series run on a field much larger than it was trained on makes emission in the
        // large empty areas and far sidelobes it never saw (a 512 series diverged at 2048):
        // its model is kept to where the data show emission unless the user says otherwise.
        // A series may name its own level, chosen on its validation sets (its manifest's
        // `auto_mask`).
        let auto_mask = match config.given_auto_mask()? {
            Some(s) => Some(s).filter(|&s| s > 0.0),
            None => match largest.filter(|&t| size > 2 * t) {
                Some(t) => {
                    let sigmas = series.auto_mask.unwrap_or(DEFAULT_AUTO_MASK);
                    log::info!("series '{}' was trained for {t} x {t}: on the {size} x {size} image its model is kept to where the data show emission (auto_mask {sigmas}; auto_mask 0 turns that off)", series.name);
                    Some(sigmas)
                }
                None => series.auto_mask.inspect(|sigmas| {
                    log::info!("series '{}' keeps its model to where the data show emission (its manifest's auto_mask {sigmas}; auto_mask 0 turns that off)", series.name);
                }),
            },
        };
        // Said per job (its log line and its metrics), before its first network.
        let size_warning = match &tiling {
            Some(tiling) => {
                log::info!("series '{}' was trained for {t} x {t}: its networks run over the {size} x {size} image in {} tiles of {t} x {t} (overlap {} pixels)", series.name, tiling.count(), tiling.overlap, t = tiling.tile);
                None
            }
            None => series.check_size(size)?,
        };
        let network_edge = tiling.as_ref().map_or(size, |t| t.tile);
        // What the pipeline fixes (weighting, a super-resolution factor) is refused here, before
        // any data are read, under `validity: error`; each job is checked with what only its
        // data tell (telescope, the pixel's super-resolution) before its first network.
        let problems = series.validity_problems(setup);
        if !problems.is_empty() && config.validity == ValidityMode::Error {
            return Err(Error::parameter("validity", format!("series '{}' was not trained for this pipeline: {}", series.name, problems.join("; "))));
        }
        let per_realisation = match config.networks {
            None => series.len(),
            Some(0) => return Err(Error::parameter("networks", "expected at least 1")),
            Some(n) if n > series.len() => {
                return Err(Error::parameter("networks", format!("series '{}' has {} networks, asked for {n}", series.name, series.len())));
            }
            Some(n) => n,
        };
        let chosen: Vec<usize> = match config.realisation {
            None => (0..series.realisations).collect(),
            Some(r) if (1..=series.realisations).contains(&r) => vec![r - 1],
            Some(r) => return Err(Error::parameter("realisation", format!("series '{}' has realisations 1..={}, asked for {r}", series.name, series.realisations))),
        };
        let plan: Vec<Vec<PathBuf>> = chosen.iter().flat_map(|&r| series.realisation(r)[..per_realisation].to_vec()).collect();
        let iterations = plan.len();
        let pad = series.edge_padding;
        if pad >= network_edge {
            return Err(Error::parameter(
                "edge_padding",
                format!("series '{}' pads its networks' inputs by {pad} pixels, which a {network_edge} x {network_edge} image cannot mirror (at most {})", series.name, network_edge - 1),
            ));
        }
        let signatures = plan
            .iter()
            .map(|layers| layers.iter().map(|file| check_network(file, network_edge + 2 * pad)).collect::<Result<Vec<_>>>())
            .collect::<Result<Vec<_>>>()?;
        crate::limits::check_threads(config.threads).map_err(|m| Error::parameter("threads", m))?;
        let threads = if config.threads > 0 { config.threads } else { pipeline_threads };
        let runtime = Runtime::select(config.backend, threads)?.with_graph_optimization(config.graph_optimization);
        log::info!(
            "series '{}' ({}, {per_realisation} iterations x {} realisation(s), {}), inference by {}",
            series.name,
            series.origin,
            chosen.len(),
            arch_name(series.architecture),
            runtime.describe()
        );
        if matches!(runtime, Runtime::Ort { .. }) {
            let mapped: Vec<_> = signatures.iter().flatten().filter_map(|s| s.mapped.as_ref()).collect();
            let mb = mapped.iter().map(|m| m.bytes).sum::<u64>() as f64 / 1e6;
            log::debug!("weights mapped from the files, not copied: {} of {} networks ({mb:.0} MB)", mapped.len(), signatures.iter().flatten().count());
        }
        Ok(OnnxStep {
            series,
            runtime,
            size,
            pad,
            iterations,
            per_realisation,
            plan,
            resident: Vec::new(),
            signatures,
            prefetch: config.prefetch,
            interleaved: false,
            pending: None,
            last_job: None,
            walking: Default::default(),
            setup: setup.clone(),
            validity: config.validity,
            size_warning,
            tiling,
            auto_mask,
            emission: Default::default(),
        })
    }

    fn network(&mut self, job: &str, iteration: usize, layer: usize) -> Result<&mut Box<dyn Network>> {
        let key = (iteration, layer);
        // One job walks the series in order until another job's call comes between two of its
        // own: one job at network 5 while the next is at 1. (A job that stopped early never
        // comes back, so it does not count.)
        let returning = self.walking.contains(job) && self.last_job.as_deref() != Some(job);
        if !self.interleaved && returning {
            log::debug!("jobs interleave through the series: prefetching off, the two most recently used networks stay resident");
            self.interleaved = true;
        }
        if self.successor(key).is_some() {
            self.walking.insert(job.to_string());
        } else {
            self.walking.remove(job);
        }
        self.last_job = Some(job.to_string());
        // A background load always ends as a resident network, never detached: at most RESIDENT
        // networks exist at any time.
        if let Some((k, handle)) = self.pending.take() {
            let net = handle.join().unwrap_or_else(|_| Err(Error::input(self.file(k), "loading the network panicked")))?;
            self.resident.push((k, net));
        }
        if !self.interleaved {
            // Walking in order, the networks before this one are not needed again: keeping one
            // would hold its weights (and, memory-mapped, every page the run touched) through
            // this network's inference for nothing.
            self.resident.retain(|(k, _)| *k == key);
        }
        if let Some(pos) = self.resident.iter().position(|(k, _)| *k == key) {
            let entry = self.resident.remove(pos);
            self.resident.push(entry);
        } else {
            // Free before loading, so that at most RESIDENT networks exist even while loading.
            if self.resident.len() >= RESIDENT {
                self.resident.remove(0);
            }
            let net = self.load(key)?;
            self.resident.push((key, net));
        }
        if self.prefetch && !self.interleaved {
            self.prefetch_after(key);
        }
        Ok(&mut self.resident.last_mut().expect("present or just pushed").1)
    }

    /// The network after `key` in the series, if any.
    fn successor(&self, (iteration, layer): Key) -> Option<Key> {
        if layer + 1 < self.plan[iteration - 1].len() {
            Some((iteration, layer + 1))
        } else if iteration < self.iterations {
            Some((iteration + 1, 0))
        } else {
            None
        }
    }

    fn file(&self, (iteration, layer): Key) -> PathBuf {
        self.plan[iteration - 1][layer].clone()
    }

    /// The edge of the images the networks run on: the job's, padded by the series'
    /// `edge_padding` on each side.
    fn network_size(&self) -> usize {
        self.tiling.as_ref().map_or(self.size, |t| t.tile) + 2 * self.pad
    }

    fn load(&self, key: Key) -> Result<Box<dyn Network>> {
        let started = std::time::Instant::now();
        let path = self.file(key);
        let net = self.runtime.load(&path, self.network_size(), &self.signatures[key.0 - 1][key.1])?;
        // Part of the step's seconds; logged so inference and loading can be told apart.
        log::debug!("loaded {} in {:.3} s", path.display(), started.elapsed().as_secs_f64());
        Ok(net)
    }

    /// Start loading the network after `key` on a background thread (only `key` is resident).
    fn prefetch_after(&mut self, key: Key) {
        let Some(next) = self.successor(key) else { return };
        let (runtime, path, size, signature) = (self.runtime.clone(), self.file(next), self.network_size(), self.signatures[next.0 - 1][next.1].clone());
        let spawned = std::thread::Builder::new().name("r2d2-prefetch".into()).spawn(move || {
            let started = std::time::Instant::now();
            let net = runtime.load(&path, size, &signature);
            log::debug!("loaded {} in {:.3} s (in the background)", path.display(), started.elapsed().as_secs_f64());
            net
        });
        // Without a thread (a limited address space) the next network loads when it is needed.
        match spawned {
            Ok(handle) => self.pending = Some((next, handle)),
            Err(e) => log::debug!("no background load of the next network: {e}"),
        }
    }

    /// The orientation network `iteration` of the plan sees its images in (the series'
    /// cycle restarts with each realisation).
    fn orientation(&self, iteration: usize) -> super::series::Orientation {
        let cycle = &self.series.orientation_cycle;
        if cycle.is_empty() {
            return super::series::Orientation::Identity;
        }
        cycle[((iteration - 1) % self.per_realisation) % cycle.len()]
    }

    fn run_network(&mut self, job: &str, iteration: usize, layer: usize, first: &[f64], second: &[f64], alpha: f64) -> Result<Vec<f64>> {
        let orientation = self.orientation(iteration);
        let mut input = Vec::with_capacity(2 * first.len());
        input.extend(first.iter().map(|v| (v / alpha) as f32));
        input.extend(second.iter().map(|v| (v / alpha) as f32));
        // The whole image, or one tile of it.
        let n = self.network_size() - 2 * self.pad;
        let input = orientation.apply(input, n);
        let output = if self.pad == 0 {
            self.network(job, iteration, layer)?.run(&input)?
        } else {
            let pad = self.pad;
            let padded: Vec<f32> = input.chunks_exact(n * n).flat_map(|channel| mirror_pad(channel, n, pad)).collect();
            crop(&self.network(job, iteration, layer)?.run(&padded)?, self.network_size(), pad)
        };
        let output = orientation.inverse().apply(output, n);
        if let Some(bad) = output.iter().position(|v| !v.is_finite()) {
            let path = self.plan[iteration - 1][layer].clone();
            return Err(super::runtime::OnnxError::Output { path, message: format!("network output is not finite at pixel {bad} (iteration {iteration})") }.into());
        }
        Ok(output.into_iter().map(f64::from).collect())
    }
}

/// A background load still running when the step goes is waited for, so no network outlives
/// the step (nor runs inside ONNX Runtime while the process exits).
impl Drop for OnnxStep {
    fn drop(&mut self) {
        if let Some((_, handle)) = self.pending.take() {
            let _ = handle.join();
        }
    }
}

/// The `n x n` image extended by `pad` pixels on every side, mirrored about its edge rows and
/// columns (`pad < n`): the edge pixel is not repeated, as numpy's `reflect`.
fn mirror_pad(image: &[f32], n: usize, pad: usize) -> Vec<f32> {
    let m = n + 2 * pad;
    let source = |k: usize| -> usize {
        let k = k as isize - pad as isize;
        let last = n as isize - 1;
        (if k < 0 { -k } else if k > last { 2 * last - k } else { k }) as usize
    };
    let mut out = Vec::with_capacity(m * m);
    for i in 0..m {
        let row = &image[source(i) * n..][..n];
        out.extend((0..m).map(|j| row[source(j)]));
    }
    out
}

/// The central `(m - 2 pad)^2` pixels of an `m x m` image.
fn crop(image: &[f32], m: usize, pad: usize) -> Vec<f32> {
    let n = m - 2 * pad;
    (pad..pad + n).flat_map(|i| image[i * m + pad..][..n].iter().copied()).collect()
}

fn arch_name(a: Architecture) -> &'static str {
    match a {
        Architecture::R2d2 => "R2D2",
        Architecture::R3d3 => "R3D3",
    }
}

fn mean(x: &[f64]) -> f64 {
    x.iter().sum::<f64>() / x.len().max(1) as f64
}

/// Added to the mean, as the reference does, so an all-zero image gives a finite alpha.
const NORMALISATION_EPSILON: f64 = 1e-10;

/// The normalisation alpha: the mean of `image` (the dirty image at iteration 1, else the
/// current model) plus a tiny epsilon, as the reference computes it, where the mean is
/// positive; its magnitude where it is not. A dirty image without baselines shorter than one
/// over its field (missing short spacings, or a field wider than the series' trained one) can
/// have a negative mean; the reference divides by it signed, which hands the networks their
/// input upside down (one sky in an empty 2048 field: residual ratio 35 at network 1). The
/// trained networks are positively homogeneous (the same residuals to five digits for any
/// positive alpha), so the magnitude gives what they were trained to give.
fn normalisation(image: &[f64], what: &str, iteration: usize, path: &Path) -> Result<f64> {
    let m = mean(image);
    if !m.is_finite() {
        return Err(Error::input(path, format!("cannot normalise the input of iteration {iteration}: the mean of the {what} is {m}")));
    }
    if m <= 0.0 {
        log::warn!("iteration {iteration}: the mean of the {what} is {m:.3e} (not positive); normalising by its magnitude (the reference divides by it signed, turning the networks' input upside down)");
    }
    Ok(m.abs() + NORMALISATION_EPSILON)
}

/// R2D2's update from a network's normalised increment: `x_i = max(0, (N_i + x_{i-1} / alpha) alpha)`.
fn next_estimate(model: &[f64], increment: &[f64], alpha: f64) -> Vec<f64> {
    model.iter().zip(increment).map(|(x, d)| ((d + x / alpha) * alpha).max(0.0)).collect()
}

impl OnnxStep {
    /// The series' trained image size nearest the image's (its weighting grid's field).
    pub(crate) fn trained_size(&self) -> Option<usize> {
        self.series.nearest_trained_size(self.size)
    }

    pub(crate) fn series_name(&self) -> &str {
        &self.series.name
    }

    /// Where the job's uniform or Briggs weights were made on a uv grid other than the one the
    /// series was trained with (the default grid of its trained field nearest the image size;
    /// a weighting other than the series' own is the domain check's to say):
    /// the same data then have another PSF than any the series saw. A 512 series at 1024 pixels
    /// with the default grid diverges at its first network; on its trained field's grid it
    /// converges.
    fn weighting_grid_problem(&self, job_cells: Option<usize>) -> Option<String> {
        let (cells, trained) = (job_cells?, self.trained_size()?);
        let trained_cells = crate::weighting::cells_of(crate::weighting::DEFAULT_GRID_FACTOR, trained);
        if cells == trained_cells {
            return None;
        }
        let factor = crate::weighting::grid_factor_of_trained_field(trained, self.size);
        Some(format!(
            "series '{}' was trained with weights made on the uv grid of its {trained} x {trained} field ({trained_cells} cells across); this job's were made on {cells} cells, so its PSF is not one the series saw and its image may be wrong: give the weighting stage `grid_factor: {factor}` (that field's uv cell at {size} x {size}; `r2d2 image` does so by itself)",
            self.series.name,
            size = self.size,
        ))
    }

    /// Whether a network step needs `D` between its layers (R3D3's data fidelity), which only
    /// the engine's own operator gives.
    pub(crate) fn needs_d_between_layers(&self) -> bool {
        self.series.architecture == Architecture::R3d3
    }
}

impl NetworkStep for OnnxStep {
    fn series_length(&self) -> usize {
        self.iterations
    }

    fn domain_problems(&self, job: &JobDomain<'_>) -> Result<Vec<String>> {
        let setup = ImagingSetup {
            telescope: (!job.telescope.trim().is_empty()).then(|| job.telescope.to_string()),
            superresolution: job.superresolution.or(self.setup.superresolution),
            track_hours: job.track_hours,
            integration_s: job.integration_s,
            ..self.setup.clone()
        };
        let problems = self.series.validity_problems(&setup);
        let mut warnings: Vec<String> = self.size_warning.iter().cloned().collect();
        // The series normalises its first input by the dirty image's mean, positive in every
        // observation it was trained on (their short baselines measure the total flux); a mean
        // at or below 0 means the data lack them, and the networks see an input they never saw.
        if let Some(m) = job.dirty_mean.filter(|m| *m <= 0.0) {
            warnings.push(format!(
                "the dirty image's mean is {m:.3e}, not positive: the data lack baselines shorter than one over the field, which the observations series '{}' was trained on had (missing short spacings, or a field wider than its trained one); its input is normalised by that mean's magnitude, and its image may be wrong; the step `clean` does not depend on it",
                self.series.name
            ));
        }
        if let Some(problem) = self.weighting_grid_problem(job.weighting_cells) {
            warnings.push(problem);
        }
        // Data that name no telescope cannot be checked against the series' telescopes: the
        // job says so, since a series run on another telescope's data gives a confident image.
        if setup.telescope.as_deref().and_then(crate::vis::named_telescope).is_none() && !self.series.telescopes().is_empty() {
            warnings.push(format!(
                "the data name no telescope, so nothing checks them against series '{}', trained for {}: from another telescope its image may be wrong (the step `clean` images any telescope's data)",
                self.series.name,
                self.series.telescopes().join(", ")
            ));
        }
        if problems.is_empty() {
            return Ok(warnings);
        }
        let domain = self.series.manifest.as_ref().and_then(|m| m.validity.as_ref()).map(|v| v.summary()).unwrap_or_default();
        let mut message = format!("series '{}' was not trained for this job: {} (its domain: {domain})", self.series.name, problems.join("; "));
        if let Some(other) = super::series::covering_series(self.size, &setup, &self.series.name) {
            message.push_str(&format!("; series '{other}' was trained for it (the step `{other}`, or `series: {other}`)"));
        }
        match self.validity {
            ValidityMode::Error => Err(Error::parameter("validity", message)),
            ValidityMode::Warn => {
                warnings.push(format!("{message}; its image may be wrong, `validity: error` refuses such jobs"));
                Ok(warnings)
            }
        }
    }

    fn describe(&self) -> Option<serde_json::Value> {
        let domain = self.series.manifest.as_ref().and_then(|m| m.validity.as_ref());
        Some(serde_json::json!({"kind": "series", "series": self.series.name, "networks": self.iterations, "domain": domain}))
    }

    fn realisations(&self) -> usize {
        self.iterations / self.per_realisation
    }

    fn early_stop_from(&self) -> usize {
        self.series.early_stop_from
    }

    fn auto_mask(&self) -> Option<f64> {
        self.auto_mask
    }

    fn step(&mut self, iteration: usize, input: &StepInput<'_>) -> Result<Vec<f64>> {
        let Some(sigmas) = self.auto_mask else {
            return self.next_image(iteration, input, None);
        };
        let n = input.size;
        // A job's mask starts empty at its first network, and is grown before the network
        // runs, from what the network sees, so that tiles wholly outside it need not run.
        let mut mask = match self.emission.remove(input.job) {
            Some(mask) if iteration > 1 => mask,
            _ => EmissionMask::new(n, main_lobe_fwhm_px(input.psf, n), sigmas),
        };
        let joined = mask.grow(if iteration == 1 { input.dirty } else { input.residual });
        log::debug!("job {}: network {iteration}: {joined} pixels joined the emission mask ({:.2} % of the image)", input.job, 100.0 * mask.fraction());
        if iteration == 1 && joined == 0 {
            log::warn!("job {}: nothing in the dirty image stands above auto_mask {sigmas} noise sigmas at the beam's scale or wider: the series' model stays empty until something in its residual does (auto_mask 0 turns the mask off)", input.job);
        }
        let mut model = self.next_image(iteration, input, Some(mask.inside()))?;
        model.iter_mut().zip(mask.inside()).filter(|(_, inside)| !**inside).for_each(|(x, _)| *x = 0.0);
        if iteration < self.iterations {
            self.emission.insert(input.job.to_string(), mask);
        }
        Ok(model)
    }
}

impl OnnxStep {
    /// The series' next image `x_i` for `input`, before any mask. Where an emission mask is
    /// given (true inside), tiles with no pixel inside it are not run: the mask sets their
    /// pixels to 0 whatever a network makes there (and those pixels come out 0).
    fn next_image(&mut self, iteration: usize, input: &StepInput<'_>, mask: Option<&[bool]>) -> Result<Vec<f64>> {
        if iteration == 0 || iteration > self.iterations {
            return Err(Error::parameter("iteration", format!("expected 1..={}, got {iteration}", self.iterations)));
        }
        if input.size != self.size {
            return Err(Error::parameter("image size", format!("the series was prepared for {0} x {0}, the job is {1} x {1}", self.size, input.size)));
        }
        let path = self.plan[iteration - 1][0].clone();
        // Each realisation starts again from the dirty image (the stage resets the job).
        let first = (iteration - 1) % self.per_realisation == 0;
        match self.series.architecture {
            Architecture::R2d2 => {
                if mask.is_some_and(|mask| !mask.contains(&true)) {
                    // Nothing found yet: the mask would set every pixel to 0.
                    return Ok(vec![0.0; input.model.len()]);
                }
                let zero;
                let (image, second, what) = if first {
                    zero = vec![0.0; input.dirty.len()];
                    (input.dirty, zero.as_slice(), "dirty image")
                } else {
                    (input.model, input.residual, "image")
                };
                let alpha = normalisation(image, what, iteration, &path)?;
                let Some(tiling) = self.tiling.clone() else {
                    let increment = self.run_network(input.job, iteration, 0, image, second, alpha)?;
                    return Ok(next_estimate(input.model, &increment, alpha));
                };
                // Each tile's next estimate, as the series makes it for a field of its size,
                // blended into the image's.
                let (mut sum, mut weights) = (vec![0.0; input.model.len()], vec![0.0; input.model.len()]);
                let origins = tiling.origins();
                let mut skipped = 0;
                for &(x0, y0) in &origins {
                    if mask.is_some_and(|mask| !tiling.any_set(mask, x0, y0)) {
                        skipped += 1;
                        continue;
                    }
                    // Normalised by the whole image's mean, as without tiles: the networks are
                    // near enough homogeneous that a tile's own mean gave the same residuals.
                    let (a, b) = (tiling.extract(image, x0, y0), tiling.extract(second, x0, y0));
                    let increment = self.run_network(input.job, iteration, 0, &a, &b, alpha)?;
                    let x = tiling.extract(input.model, x0, y0);
                    tiling.accumulate(&next_estimate(&x, &increment, alpha), x0, y0, &mut sum, &mut weights);
                }
                if skipped > 0 {
                    log::debug!("job {}: network {iteration}: {skipped} of {} tiles outside the emission mask not run", input.job, origins.len());
                }
                Ok(sum.iter().zip(&weights).map(|(s, w)| if *w > 0.0 { s / w } else { 0.0 }).collect())
            }
            Architecture::R3d3 => {
                let layers = self.plan[iteration - 1].len();
                let psf = input.psf_convolution;
                let mut image = input.model.to_vec();
                let mut residual = if first { input.dirty.to_vec() } else { input.residual.to_vec() };
                let mut alpha = if first {
                    normalisation(input.dirty, "dirty image", iteration, &path)?
                } else {
                    normalisation(&image, "image", iteration, &path)?
                };
                for layer in 0..layers {
                    let increment = self.run_network(input.job, iteration, layer, &residual, &image, alpha)?;
                    for (x, d) in image.iter_mut().zip(&increment) {
                        *x = (*x / alpha + d) * alpha;
                    }
                    if layer + 1 < layers {
                        // Data fidelity between layers: the residual of the current image.
                        let dx = psf.apply(&image);
                        residual = input.dirty.iter().zip(&dx).map(|(d, v)| d - v).collect();
                        alpha = normalisation(&image, "image", iteration, &path)?;
                    }
                }
                Ok(image.into_iter().map(|v| v.max(0.0)).collect())
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::operator::PsfConvolution;
    use std::sync::OnceLock;

    /// The tiny analytic networks of `tests/make_test_models.py`, generated once per test run.
    /// Python with the `onnx` package is a test requirement (tests/requirements.txt): missing,
    /// the tests fail saying so rather than skip.
    pub(crate) fn test_models() -> &'static Path {
        static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
        DIR.get_or_init(|| {
            let dir = tempfile::tempdir().expect("temp dir");
            let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/make_test_models.py");
            let out = std::process::Command::new("python3").arg(&script).arg(dir.path()).output().expect("python3 runs (a test requirement)");
            assert!(out.status.success(), "{} failed (pip install -r tests/requirements.txt):\n{}", script.display(), String::from_utf8_lossy(&out.stderr));
            dir
        })
        .path()
    }

    /// A deterministic `[1, 2, 64, 64]` input for the test U-Net.
    pub(crate) fn unet_input() -> Vec<f32> {
        (0..2 * 64 * 64).map(|k| ((k * 7919 % 1000) as f32 / 1000.0).powi(2)).collect()
    }

    const N: usize = 32;

    /// A PSF over twice the field, peak 1 at (N, N): a narrow Gaussian (sigma 0.6 px) minus a
    /// broad one (sigma 2 px, 5 %) off centre, so the residual has structure of both signs.
    /// Its spectrum lies in about (1, 2.3), so the test networks' gain of 0.5 is a convergent
    /// Landweber step (a wider PSF, like a real beam of many pixels, would make it diverge).
    fn psf_2n() -> Vec<f64> {
        let m = 2 * N;
        let mut p = vec![0.0; m * m];
        for y in 0..m {
            for x in 0..m {
                let d2 = (x as f64 - N as f64).powi(2) + (y as f64 - N as f64).powi(2);
                let ring = if d2 > 0.0 { 0.05 * (-d2 / (2.0 * 2.0 * 2.0)).exp() } else { 0.0 };
                p[y * m + x] = (-d2 / (2.0 * 0.6 * 0.6)).exp() - ring;
            }
        }
        p
    }

    /// `D x` by direct summation (independent of the FFT-based operator).
    fn direct_d(psf: &[f64], x: &[f64]) -> Vec<f64> {
        let m = 2 * N;
        let mut out = vec![0.0; N * N];
        for py in 0..N {
            for px in 0..N {
                let mut s = 0.0;
                for qy in 0..N {
                    for qx in 0..N {
                        s += psf[(py + N - qy) * m + (px + N - qx)] * x[qy * N + qx];
                    }
                }
                out[py * N + px] = s;
            }
        }
        out
    }

    /// `dirty - D x`, with the direct-sum D.
    fn residual(psf: &[f64], dirty: &[f64], x: &[f64]) -> Vec<f64> {
        dirty.iter().zip(direct_d(psf, x)).map(|(d, v)| d - v).collect()
    }

    fn sky() -> Vec<f64> {
        let mut x = vec![0.0; N * N];
        for (i, (px, py, f)) in [(5, 7, 1.0), (20, 12, 0.4), (16, 16, 2.0), (25, 26, 0.05), (9, 24, 0.7)].into_iter().enumerate() {
            x[py * N + px] = f + i as f64 * 1e-3;
        }
        x
    }

    fn rel(a: &[f64], b: &[f64]) -> f64 {
        let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
        let den: f64 = b.iter().map(|y| y * y).sum();
        (num / den).sqrt()
    }

    /// The step's configuration in the tests: tract, one thread, prefetching, warnings only.
    fn test_config(series: &Path) -> OnnxConfig {
        OnnxConfig {
            series: series.to_path_buf(),
            backend: BackendChoice::Tract,
            threads: 1,
            networks: None,
            prefetch: true,
            graph_optimization: GraphOptimization::default(),
            realisation: None,
            validity: ValidityMode::Warn,
            fits_mask: None,
            auto_mask: None,
            tiles: TileMode::Auto,
        }
    }

    fn run_series(series: &Path, backend: BackendChoice, psf: &[f64], dirty: &[f64], prefetch: bool) -> Vec<Vec<f64>> {
        if backend != BackendChoice::Tract {
            crate::steps::onnx::runtime::use_onnx_runtime_for_tests();
        }
        let config = OnnxConfig { backend, prefetch, ..test_config(series) };
        run_with(&mut OnnxStep::new(&config, N, 1, &ImagingSetup::default()).unwrap(), psf, dirty)
    }

    #[test]
    fn r2d2_loop_matches_projected_landweber_on_both_backends() {
        let psf = psf_2n();
        let dirty = direct_d(&psf, &sky());
        // Independent: x_i = max(0, x + 0.5 r + 0.01 alpha_i), alpha_1 = mean(dirty), r_0 = dirty.
        let mut expected = Vec::new();
        let (mut x, mut r) = (vec![0.0; N * N], dirty.clone());
        for i in 1..=4 {
            let alpha = if i == 1 { mean(&dirty) } else { mean(&x) };
            x = x.iter().zip(&r).map(|(x, r)| (x + 0.5 * r + 0.01 * alpha).max(0.0)).collect();
            r = residual(&psf, &dirty, &x);
            expected.push(x.clone());
        }
        for backend in [BackendChoice::Ort, BackendChoice::Tract] {
            for dir in ["landweber", "landweber-ref"] {
                // Prefetching changes when networks load, never what they compute.
                for prefetch in [true, false] {
                    let got = run_series(&test_models().join(dir), backend, &psf, &dirty, prefetch);
                    for (i, (g, e)) in got.iter().zip(&expected).enumerate() {
                        let err = rel(g, e);
                        assert!(err < 1e-5, "{backend:?} {dir} prefetch {prefetch} iteration {}: relative error {err:.2e}", i + 1);
                    }
                }
            }
        }
        // The series does something: the residual falls.
        let r1: f64 = residual(&psf, &dirty, &expected[0]).iter().map(|v| v * v).sum();
        let r4: f64 = residual(&psf, &dirty, &expected[3]).iter().map(|v| v * v).sum();
        assert!(r4 < 0.5 * r1, "Landweber reduces the residual: {r1} -> {r4}");
    }

    /// The Landweber series as if trained at 16 x 16 (its manifest's `image_sizes`).
    fn landweber_trained_at_16() -> tempfile::TempDir {
        let series = landweber_with("");
        let path = series.path().join("manifest.yaml");
        let manifest = std::fs::read_to_string(&path).unwrap();
        let sizes = manifest.lines().find(|l| l.starts_with("image_sizes:")).unwrap().to_string();
        std::fs::write(&path, manifest.replace(&sizes, "image_sizes: [16]")).unwrap();
        series
    }

    #[test]
    fn an_image_larger_than_the_trained_size_runs_in_blended_tiles() {
        let psf = psf_2n();
        let dirty = direct_d(&psf, &sky());
        let series = landweber_trained_at_16();
        // `auto` runs an image up to twice the trained size whole, `on` in tiles.
        assert!(OnnxStep::new(&test_config(series.path()), N, 1, &ImagingSetup::default()).unwrap().tiling.is_none());
        let on = OnnxConfig { tiles: TileMode::On, ..test_config(series.path()) };
        let step = OnnxStep::new(&on, N, 1, &ImagingSetup::default()).unwrap();
        let tiling = step.tiling.clone().expect("32 x 32 with a series trained at 16 runs in tiles");
        assert_eq!((tiling.tile, tiling.overlap, tiling.count()), (16, 4, 9));
        assert!(step.size_warning.is_none(), "tiles of the trained size: no warning of a size it was not trained for");
        // A pointwise network normalised by the whole image's mean gives, tile by tile, exactly
        // what it gives on the whole image: the blend is seamless.
        let whole = {
            let off = OnnxConfig { tiles: TileMode::Off, ..test_config(series.path()) };
            let mut step = OnnxStep::new(&off, N, 1, &ImagingSetup::default()).unwrap();
            assert!(step.tiling.is_none() && step.size_warning.is_some());
            run_with(&mut step, &psf, &dirty)
        };
        let tiled = run_with(&mut OnnxStep::new(&on, N, 1, &ImagingSetup::default()).unwrap(), &psf, &dirty);
        for (i, (t, w)) in tiled.iter().zip(&whole).enumerate() {
            assert!(rel(t, w) < 1e-6, "iteration {}: tiled vs whole {:.2e}", i + 1, rel(t, w));
        }
        // A 64 x 64 image (more than twice 16) is tiled by `auto`.
        assert!(OnnxStep::new(&test_config(series.path()), 64, 1, &ImagingSetup::default()).unwrap().tiling.is_some());
    }

    /// With an emission mask, tiles wholly outside it are not run, and the models are those
    /// of every tile run and the mask applied after.
    #[test]
    fn tiles_outside_the_emission_mask_are_not_run_and_change_nothing() {
        let psf = psf_2n();
        // One source in a corner, over a faint deterministic noise.
        let mut sky = vec![0.0; N * N];
        sky[5 * N + 5] = 1.0;
        let noise = |k: usize| 1e-3 * (((k * 7919) % 1000) as f64 / 500.0 - 1.0);
        let dirty: Vec<f64> = direct_d(&psf, &sky).iter().enumerate().map(|(k, v)| v + noise(k)).collect();
        let series = landweber_trained_at_16();
        let masked = OnnxConfig { tiles: TileMode::On, auto_mask: Some(5.0), ..test_config(series.path()) };
        let got = run_with(&mut OnnxStep::new(&masked, N, 1, &ImagingSetup::default()).unwrap(), &psf, &dirty);
        let open = OnnxConfig { tiles: TileMode::On, auto_mask: Some(0.0), ..test_config(series.path()) };
        let mut every_tile = OnnxStep::new(&open, N, 1, &ImagingSetup::default()).unwrap();
        let tiling = every_tile.tiling.clone().unwrap();
        let convolution = PsfConvolution::new(N, &psf).unwrap();
        let psf_n = vec![0.0; N * N];
        let mut mask = EmissionMask::new(N, main_lobe_fwhm_px(&psf_n, N), 5.0);
        let (mut model, mut residual) = (vec![0.0; N * N], dirty.clone());
        for (i, got) in got.iter().enumerate() {
            let input = StepInput { job: "job", size: N, model: &model, residual: &residual, dirty: &dirty, psf: &psf_n, psf_2n: &psf, psf_convolution: &convolution, mask: None };
            mask.grow(if i == 0 { &dirty } else { &residual });
            let mut expected = every_tile.next_image(i + 1, &input, None).unwrap();
            expected.iter_mut().zip(mask.inside()).filter(|(_, inside)| !**inside).for_each(|(x, _)| *x = 0.0);
            assert!(rel(got, &expected) < 1e-12, "iteration {}: {:.2e}", i + 1, rel(got, &expected));
            model = expected;
            residual = self::residual(&psf, &dirty, &model);
        }
        let outside = tiling.origins().iter().filter(|&&(x0, y0)| !tiling.any_set(mask.inside(), x0, y0)).count();
        assert!(outside > 0 && model.iter().any(|&v| v > 0.0), "{outside} of {} tiles outside the mask", tiling.count());
    }

    fn run_with(step: &mut OnnxStep, psf: &[f64], dirty: &[f64]) -> Vec<Vec<f64>> {
        let psf_n = vec![0.0; N * N];
        let convolution = PsfConvolution::new(N, psf).unwrap();
        let (mut model, mut residual) = (vec![0.0; N * N], dirty.to_vec());
        let mut models = Vec::new();
        for i in 1..=step.series_length() {
            let input = StepInput { job: "job", size: N, model: &model, residual: &residual, dirty, psf: &psf_n, psf_2n: psf, psf_convolution: &convolution, mask: None };
            model = step.step(i, &input).unwrap();
            assert!(step.resident.len() + step.pending.is_some() as usize <= RESIDENT);
            residual = self::residual(psf, dirty, &model);
            models.push(model.clone());
        }
        models
    }

    /// A copy of the Landweber test series with `extra` added to its manifest.
    fn landweber_with(extra: &str) -> tempfile::TempDir {
        let dir = test_models().join("landweber");
        let series = tempfile::tempdir().unwrap();
        for f in ["lw1.onnx", "lw2.onnx", "lw3.onnx", "lw4.onnx"] {
            std::fs::copy(dir.join(f), series.path().join(f)).unwrap();
        }
        let manifest = std::fs::read_to_string(dir.join("manifest.yaml")).unwrap();
        std::fs::write(series.path().join("manifest.yaml"), format!("{manifest}{extra}")).unwrap();
        series
    }

    /// `series` (a variant of the pixelwise Landweber series) gives the plain series' models
    /// on both backends.
    fn assert_models_as_plain_landweber(series: &Path) {
        let psf = psf_2n();
        let dirty = direct_d(&psf, &sky());
        for backend in [BackendChoice::Ort, BackendChoice::Tract] {
            let variant = run_series(series, backend, &psf, &dirty, true);
            let plain = run_series(&test_models().join("landweber"), backend, &psf, &dirty, true);
            for (i, (a, b)) in variant.iter().zip(&plain).enumerate() {
                assert!(rel(a, b) < 1e-6, "{} {backend:?} iteration {}: {:.2e}", series.display(), i + 1, rel(a, b));
            }
        }
    }

    #[test]
    fn an_orientation_cycle_turns_each_networks_images_and_turns_the_output_back() {
        // The Landweber networks act pixel by pixel, so whatever turn a network's images are
        // given in, the series' models are unchanged, provided each output is turned back by
        // the inverse of its input's turn (a quarter turn undone by the same quarter turn, or
        // by none, would leave the model turned).
        let series = landweber_with("orientation_cycle: [rotate_90, mirror_x, rotate_270]\n");
        // The sky is asymmetric: a model left turned would differ from the plain series'.
        assert_models_as_plain_landweber(series.path());
        let config = test_config(series.path());
        let step = OnnxStep::new(&config, N, 1, &ImagingSetup::default()).unwrap();
        use crate::steps::onnx::series::Orientation::*;
        assert_eq!((1..=4).map(|i| step.orientation(i)).collect::<Vec<_>>(), [Rotate90, MirrorX, Rotate270, Rotate90], "network k takes entry (k - 1) mod 3");
    }

    #[test]
    fn edge_padding_mirrors_each_input_and_crops_each_output() {
        // As numpy's `reflect`: for a pad of 2 the rows and columns are 2 1 0 1 2 1 0.
        let image: Vec<f32> = (0..9).map(|v| v as f32).collect();
        let padded = mirror_pad(&image, 3, 2);
        let source = [2usize, 1, 0, 1, 2, 1, 0];
        for i in 0..7 {
            for j in 0..7 {
                assert_eq!(padded[i * 7 + j], image[source[i] * 3 + source[j]], "({i}, {j})");
            }
        }
        assert_eq!(crop(&padded, 7, 2), image);
        // A series of pixelwise networks (1x1 convolutions) padded: the same models as unpadded.
        let series = landweber_with("edge_padding: 8\n");
        assert_models_as_plain_landweber(series.path());
        let manifest = std::fs::read_to_string(test_models().join("landweber/manifest.yaml")).unwrap();
        // More padding than the image can mirror: refused, naming the field.
        std::fs::write(series.path().join("manifest.yaml"), format!("{manifest}edge_padding: {N}\n")).unwrap();
        let config = test_config(series.path());
        let e = OnnxStep::new(&config, N, 1, &ImagingSetup::default()).err().expect("refused").to_string();
        assert!(e.contains("edge_padding") && e.contains(&format!("{N} pixels")), "{e}");
    }

    #[test]
    fn a_dirty_image_with_a_negative_mean_is_normalised_by_its_magnitude() {
        // Missing short spacings can make a dirty image's mean negative: the loop must run,
        // dividing by the mean's magnitude plus epsilon (the reference: the signed mean).
        let psf = psf_2n();
        let mut dirty = direct_d(&psf, &sky());
        let offset = 3.0 * mean(&dirty);
        dirty.iter_mut().for_each(|d| *d -= offset);
        assert!(mean(&dirty) < 0.0);
        let mut expected = Vec::new();
        let (mut x, mut r) = (vec![0.0; N * N], dirty.clone());
        for i in 1..=4 {
            let alpha = if i == 1 { mean(&dirty).abs() } else { mean(&x) } + NORMALISATION_EPSILON;
            x = x.iter().zip(&r).map(|(x, r)| ((x / alpha + 0.5 * r / alpha + 0.01) * alpha).max(0.0)).collect();
            r = residual(&psf, &dirty, &x);
            expected.push(x.clone());
        }
        assert!(expected[0].iter().any(|&v| v > 0.0), "the first iterate is not trivially zero");
        for backend in [BackendChoice::Ort, BackendChoice::Tract] {
            let got = run_series(&test_models().join("landweber"), backend, &psf, &dirty, true);
            for (i, (g, e)) in got.iter().zip(&expected).enumerate() {
                let err = rel(g, e);
                assert!(err < 1e-5, "{backend:?} iteration {}: relative error {err:.2e}", i + 1);
            }
        }
    }

    #[test]
    fn interleaved_jobs_get_the_same_images_with_at_most_two_networks_resident() {
        let psf = psf_2n();
        let dirty = direct_d(&psf, &sky());
        let series = test_models().join("landweber");
        let alone = run_series(&series, BackendChoice::Tract, &psf, &dirty, true);
        let config = test_config(&series);
        let mut step = OnnxStep::new(&config, N, 1, &ImagingSetup::default()).unwrap();
        let psf_n = vec![0.0; N * N];
        let convolution = PsfConvolution::new(N, &psf).unwrap();
        // Two jobs on the same data; job B starts when job A is at network 3.
        let mut jobs = [(vec![0.0; N * N], dirty.clone(), Vec::new()), (vec![0.0; N * N], dirty.clone(), Vec::new())];
        let order = [(0, 1), (0, 2), (1, 1), (0, 3), (1, 2), (0, 4), (1, 3), (1, 4)];
        for (job, i) in order {
            let (model, residual, models) = &mut jobs[job];
            let id = ["a", "b"][job];
            let input = StepInput { job: id, size: N, model, residual, dirty: &dirty, psf: &psf_n, psf_2n: &psf, psf_convolution: &convolution, mask: None };
            *model = step.step(i, &input).unwrap();
            assert!(step.resident.len() + step.pending.is_some() as usize <= RESIDENT, "more than {RESIDENT} networks");
            *residual = self::residual(&psf, &dirty, model);
            models.push(model.clone());
        }
        assert!(step.interleaved && step.pending.is_none(), "prefetching stops once jobs interleave");
        for (_, _, models) in &jobs {
            assert_eq!(models, &alone);
        }
    }

    #[test]
    fn one_job_keeps_only_the_running_network_and_its_successor() {
        let series = test_models().join("landweber");
        for prefetch in [true, false] {
            let config = OnnxConfig { prefetch, ..test_config(&series) };
            let mut step = OnnxStep::new(&config, N, 1, &ImagingSetup::default()).unwrap();
            for job in 0..2 {
                for i in 1..=4 {
                    step.network(&format!("job{job}"), i, 0).unwrap();
                    let resident: Vec<Key> = step.resident.iter().map(|(k, _)| *k).collect();
                    let pending = step.pending.as_ref().map(|(k, _)| *k);
                    assert_eq!(resident, [(i, 0)], "job {job}, network {i}, prefetch {prefetch}");
                    assert_eq!(pending, if prefetch && i < 4 { Some((i + 1, 0)) } else { None }, "job {job}, network {i}");
                }
            }
            assert!(!step.interleaved, "jobs one after the other are not interleaved");
        }
    }

    #[test]
    fn r3d3_components_interleave_layers_with_psf_data_fidelity() {
        let psf = psf_2n();
        let dirty = direct_d(&psf, &sky());
        let mut expected = Vec::new();
        let (mut x, mut r) = (vec![0.0; N * N], dirty.clone());
        for _component in 0..2 {
            let mut image = x.clone();
            let mut res = r.clone();
            for layer in 0..3 {
                image = image.iter().zip(&res).map(|(x, r)| x + 0.5 * r).collect();
                if layer < 2 {
                    res = residual(&psf, &dirty, &image);
                }
            }
            x = image.into_iter().map(|v| v.max(0.0)).collect();
            r = residual(&psf, &dirty, &x);
            expected.push(x.clone());
        }
        let got = run_series(&test_models().join("r3d3"), BackendChoice::Tract, &psf, &dirty, true);
        for (i, (g, e)) in got.iter().zip(&expected).enumerate() {
            // The step's between-layer residual uses the FFT convolution, the reference a direct sum.
            let err = rel(g, e);
            assert!(err < 1e-5, "component {}: relative error {err:.2e}", i + 1);
        }
    }

    #[test]
    fn native_onnx_runtime_and_tract_agree_on_a_unet() {
        let path = test_models().join("unet.onnx");
        let signature = check_network(&path, 64).unwrap();
        assert_eq!(signature.input_params[2..], [Some("H".to_string()), Some("W".to_string())], "symbolic dimensions are named");
        let input = unet_input();
        let ort = { crate::steps::onnx::runtime::use_onnx_runtime_for_tests(); Runtime::select(BackendChoice::Ort, 1) }.expect("native ONNX Runtime (pip install onnxruntime)");
        let a = ort.load(&path, 64, &signature).unwrap().run(&input).unwrap();
        let b = Runtime::Tract.load(&path, 64, &signature).unwrap().run(&input).unwrap();
        let (a, b): (Vec<f64>, Vec<f64>) = (a.into_iter().map(f64::from).collect(), b.into_iter().map(f64::from).collect());
        let err = rel(&a, &b);
        assert!(err < 1e-4, "ort vs tract: relative error {err:.2e}");
        assert!(a.iter().map(|v| v.abs()).sum::<f64>() > 1.0, "the U-Net output is not trivially zero");
    }

    #[test]
    fn external_data_networks_give_the_same_output_and_a_missing_side_file_is_refused() {
        // unet-external.onnx is unet.onnx with every weight in unet-external.onnx.data.
        let dir = tempfile::tempdir().unwrap();
        for f in ["unet.onnx", "unet-external.onnx", "unet-external.onnx.data"] {
            std::fs::copy(test_models().join(f), dir.path().join(f)).unwrap();
        }
        let input = unet_input();
        let ort = { crate::steps::onnx::runtime::use_onnx_runtime_for_tests(); Runtime::select(BackendChoice::Ort, 1) }.expect("native ONNX Runtime (pip install onnxruntime)");
        let run_both = |path: &Path| {
            let signature = check_network(path, 64).unwrap();
            let a = ort.load(path, 64, &signature).unwrap().run(&input).unwrap();
            let b = Runtime::Tract.load(path, 64, &signature).unwrap().run(&input).unwrap();
            (signature, a, b)
        };
        let (inline, ort_inline, tract_inline) = run_both(&dir.path().join("unet.onnx"));
        let path = dir.path().join("unet-external.onnx");
        let (external, ort_external, tract_external) = run_both(&path);
        assert_eq!(inline.external_bytes, 0);
        assert!(external.external_bytes > 20_000 && external.mapped.is_none(), "{external:?}");
        assert_eq!(ort_external, ort_inline, "ONNX Runtime: same output");
        assert_eq!(tract_external, tract_inline, "tract: same output");
        // A truncated or missing side file is refused before anything runs, naming it.
        let data = dir.path().join("unet-external.onnx.data");
        let len = std::fs::metadata(&data).unwrap().len();
        std::fs::OpenOptions::new().write(true).open(&data).unwrap().set_len(len - 1).unwrap();
        let e = check_network(&path, 64).unwrap_err().to_string();
        assert!(e.contains("unet-external.onnx.data") && e.contains("truncated"), "{e}");
        std::fs::remove_file(&data).unwrap();
        let e = check_network(&path, 64).unwrap_err().to_string();
        assert!(e.contains("unet-external.onnx.data") && e.contains("missing"), "{e}");
    }

    #[test]
    fn bad_networks_are_refused_before_imaging_with_the_reason() {
        let dir = test_models();
        let cases = [
            ("bad-output-channels.onnx", 64, "output: expected [1, 1, H, W]"),
            ("bad-input-channels.onnx", 64, "input: expected [1, 2, H, W]"),
            ("bad-rank.onnx", 64, "expected rank 4"),
            ("bad-corrupt.onnx", 64, "not a readable ONNX model"),
            ("fixed64.onnx", 128, "fixed image size"),
        ];
        for (file, size, needle) in cases {
            let e = check_network(&dir.join(file), size).unwrap_err().to_string();
            assert!(e.contains(file) && e.contains(needle), "{file}: {e}");
        }
        check_network(&dir.join("fixed64.onnx"), 64).unwrap();
        // Through the step: a manifest that forbids other sizes.
        let series = tempfile::tempdir().unwrap();
        for f in ["lw1.onnx", "lw2.onnx", "lw3.onnx", "lw4.onnx"] {
            std::fs::copy(dir.join("landweber").join(f), series.path().join(f)).unwrap();
        }
        let text = std::fs::read_to_string(dir.join("landweber/manifest.yaml")).unwrap().replace("any_size: true", "any_size: false");
        std::fs::write(series.path().join("manifest.yaml"), text).unwrap();
        let config = test_config(series.path());
        let e = OnnxStep::new(&config, 128, 1, &ImagingSetup::default()).err().expect("size refused").to_string();
        assert!(e.contains("[64]") && e.contains("128 x 128"), "{e}");
        let e = OnnxStep::new(&OnnxConfig { networks: Some(9), ..config.clone() }, 64, 1, &ImagingSetup::default()).err().expect("too many").to_string();
        assert!(e.contains("has 4 networks"), "{e}");
        std::fs::write(series.path().join("lw3.onnx"), b"garbage").unwrap();
        let e = OnnxStep::new(&config, 64, 1, &ImagingSetup::default()).err().expect("corrupt file refused").to_string();
        assert!(e.contains("lw3.onnx"), "{e}");
    }
}
