//! A series driven by an outside imager's major cycles (WSClean's `-python-deconvolution`
//! hook): the imager computes each residual `x_d - D x` from its visibilities with its own
//! gridder and asks for the next model; the networks, the stop rule (divergence guard and the
//! v2 rule) and the final CLEAN run here as in the engine's loop, each residual they need
//! coming from that imager's next major cycle.
//!
//! The loop is written as the engine's is, straight through, on a thread of its own: each time
//! it needs a residual it hands the model over and waits for the imager's next call.

use super::onnx::{OnnxConfig, OnnxStep};
use super::series::ImagingSetup;
use super::{JobDomain, NetworkStep, StepInput};
use crate::deconv::final_clean::{final_clean, CleanInput, FinalCleanParams};
use crate::job::{Iterate, StopReason, StopRule};
use crate::metrics::residual_ratio;
use crate::operator::PsfConvolution;
use crate::{Error, Result};
use crossbeam_channel::{bounded, Receiver, Sender};

/// What a driven series runs.
#[derive(Clone, Debug)]
pub struct DrivenConfig {
    /// The series and how its networks run (`series: auto` chooses by `size` and `setup`).
    pub step: OnnxConfig,
    /// Image size, pixels (square images only, as the series').
    pub size: usize,
    /// The job as far as the series' domain goes (telescope, super-resolution, weighting,
    /// track): the domain check's warnings come from it.
    pub setup: ImagingSetup,
    pub stop: StopRule,
    /// The final CLEAN after the series; none: the series' model is the result.
    pub final_clean: Option<FinalCleanParams>,
}

/// What the imager is to do next.
#[derive(Debug)]
pub enum Cycle {
    /// Compute the residual of this model (Jy/pixel) and call again with it.
    Evaluate(Vec<f64>),
    /// Imaging is over: this model is the result.
    Done(DrivenOutcome),
}

/// The result of a driven series.
#[derive(Clone, Debug)]
pub struct DrivenOutcome {
    pub model: Vec<f64>,
    /// Networks run, and the iterate kept (0: the empty model, also where the final CLEAN
    /// imaged the data alone after the series was rejected).
    pub networks_run: usize,
    pub kept_network: usize,
    /// Why the series stopped before its last network, if it did.
    pub stop: Option<StopReason>,
    /// The residual ratio of each network's model, in order.
    pub ratios: Vec<f64>,
    /// Major cycles the final CLEAN kept, and the residual ratio of the result.
    pub final_clean_cycles: usize,
    pub ratio: f64,
}

/// A series being driven: see the module's documentation.
pub struct DrivenSeries {
    residuals: Option<Sender<Vec<f64>>>,
    asks: Receiver<Result<Cycle>>,
    worker: Option<std::thread::JoinHandle<()>>,
    warnings: Vec<String>,
    networks: usize,
    name: String,
    trained_size: Option<usize>,
    done: bool,
}

/// The worker's side of a residual request: the model goes to the imager, its residual comes
/// back; an imager gone (the series dropped) ends the loop.
struct Imager {
    asks: Sender<Result<Cycle>>,
    residuals: Receiver<Vec<f64>>,
    n: usize,
}

impl Imager {
    fn residual_of(&self, model: &[f64]) -> Result<Vec<f64>> {
        self.asks.send(Ok(Cycle::Evaluate(model.to_vec()))).map_err(|_| gone())?;
        let residual = self.residuals.recv().map_err(|_| gone())?;
        if residual.len() != self.n * self.n {
            return Err(Error::parameter("residual", format!("expected {0} x {0} pixels, got {1}", self.n, residual.len())));
        }
        crate::sanity::check_image(&residual, self.n, "residual from the imager", "the imager's major cycle made it from the model it was given")?;
        Ok(residual)
    }
}

fn gone() -> Error {
    Error::Interrupted("the imager driving the series stopped asking for models".into())
}

/// The N x N PSF (peak at (N/2, N/2)) in the middle of a 2N x 2N one (peak at (N, N)), zero
/// beyond: what the imager gives is the PSF over the field, so the minor cycles' components
/// far from a source see a PSF cut at the field's half width; the major cycles' exact
/// residuals correct for it.
fn doubled(psf: &[f64], n: usize) -> Vec<f64> {
    let m = 2 * n;
    let mut out = vec![0.0; m * m];
    let offset = n - n / 2;
    for y in 0..n {
        out[(y + offset) * m + offset..][..n].copy_from_slice(&psf[y * n..][..n]);
    }
    out
}

impl DrivenSeries {
    /// Opens the series for `config.size` images, checks the job (`dirty`: the residual of the
    /// empty model, Jy/beam; `psf`: N x N, peak 1 at (N/2, N/2)) against its domain and starts
    /// the loop; [`DrivenSeries::next`] then gives the first model to evaluate.
    pub fn start(config: DrivenConfig, dirty: Vec<f64>, psf: Vec<f64>) -> Result<DrivenSeries> {
        let n = config.size;
        if n < 2 {
            return Err(Error::parameter("image size", format!("expected at least 2 x 2 pixels, got {n} x {n}")));
        }
        for (what, image) in [("dirty image", &dirty), ("PSF", &psf)] {
            if image.len() != n * n {
                return Err(Error::parameter(what, format!("expected {n} x {n} pixels, got {}", image.len())));
            }
            crate::sanity::check_image(image, n, what, "the imager gave it")?;
        }
        let step = OnnxStep::new(&config.step, n, 0, &config.setup)?;
        if step.realisations() != 1 || step.needs_d_between_layers() {
            return Err(Error::parameter(
                "series",
                format!("series '{}' needs the engine's own D (several realisations, or layers with data fidelity between them); an outside imager gives one residual per major cycle", step.series_name()),
            ));
        }
        let setup = &config.setup;
        let domain = JobDomain {
            telescope: setup.telescope.as_deref().unwrap_or(""),
            superresolution: setup.superresolution,
            track_hours: setup.track_hours,
            integration_s: setup.integration_s,
            dirty_mean: Some(dirty.iter().sum::<f64>() / dirty.len() as f64),
            // The outside imager weighs on its own grid, which it does not tell.
            weighting_cells: None,
        };
        let warnings = step.domain_problems(&domain)?;
        let (networks, name, trained_size) = (step.series_length(), step.series_name().to_string(), step.trained_size());
        let (ask_tx, ask_rx) = bounded(1);
        let (res_tx, res_rx) = bounded(1);
        let imager = Imager { asks: ask_tx, residuals: res_rx, n };
        let worker = std::thread::Builder::new()
            .name("r2d2-driven".into())
            .spawn(move || {
                let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| drive(step, &config, dirty, psf, &imager)))
                    .unwrap_or_else(|p| Err(Error::parameter("series", format!("the driven series panicked: {}", crate::error::panic_message(&*p)))));
                // The imager may have gone; nothing is left to tell then.
                let _ = imager.asks.send(outcome.map(Cycle::Done));
            })
            .map_err(|e| Error::OutOfMemory(format!("cannot start the driven series' thread: {e}")))?;
        Ok(DrivenSeries { residuals: Some(res_tx), asks: ask_rx, worker: Some(worker), warnings, networks, name, trained_size, done: false })
    }

    /// What the domain check found (one sentence each), to be shown to the user.
    pub fn warnings(&self) -> &[String] {
        &self.warnings
    }

    /// Networks in the series (the most major cycles it runs before the final CLEAN).
    pub fn networks(&self) -> usize {
        self.networks
    }

    pub fn series_name(&self) -> &str {
        &self.name
    }

    /// The series' trained image size nearest the image's: the imager's uniform and Briggs
    /// weights should be made on twice that many cells across, the grid it was trained with.
    pub fn trained_size(&self) -> Option<usize> {
        self.trained_size
    }

    /// The next thing to do: `residual` is that of the model last asked for (none at the first
    /// call, whose residual is the dirty image given to [`DrivenSeries::start`]).
    pub fn next(&mut self, residual: Option<Vec<f64>>) -> Result<Cycle> {
        if self.done {
            return Err(Error::parameter("major cycle", "the series has already given its result"));
        }
        if let Some(residual) = residual {
            let sent = self.residuals.as_ref().is_some_and(|s| s.send(residual).is_ok());
            if !sent {
                return Err(Error::parameter("major cycle", "the series is not waiting for a residual"));
            }
        }
        let cycle = self.asks.recv().unwrap_or_else(|_| Err(Error::parameter("series", "the driven series ended without a result")));
        if !matches!(cycle, Ok(Cycle::Evaluate(_))) {
            self.done = true;
            if let Some(worker) = self.worker.take() {
                let _ = worker.join();
            }
        }
        cycle
    }
}

impl Drop for DrivenSeries {
    fn drop(&mut self) {
        // Closing the residuals' channel ends a loop waiting for one.
        self.residuals = None;
        while self.asks.recv().is_ok() {}
        if let Some(worker) = self.worker.take() {
            let _ = worker.join();
        }
    }
}

/// The engine's loop with the imager's residuals: networks under the stop rule, the best
/// iterate kept against divergence, then the final CLEAN (from the empty model where the
/// series was rejected).
fn drive(mut step: OnnxStep, config: &DrivenConfig, dirty: Vec<f64>, psf: Vec<f64>, imager: &Imager) -> Result<DrivenOutcome> {
    let n = config.size;
    let psf_2n = doubled(&psf, n);
    let convolution = PsfConvolution::new(n, &psf_2n)?;
    let total = step.series_length();
    let (mut model, mut residual) = (vec![0.0; n * n], dirty.clone());
    let mut ratios = Vec::new();
    // The iterate of lowest residual ratio so far (none: the empty model, ratio 1).
    let mut best: Option<Iterate> = None;
    let (mut stop, mut kept_network) = (None, 0);
    for iteration in 1..=total {
        let input = StepInput {
            job: "driven",
            size: n,
            model: &model,
            residual: &residual,
            dirty: &dirty,
            psf: &psf,
            psf_2n: &psf_2n,
            psf_convolution: &convolution,
            mask: None,
        };
        let next = step.step(iteration, &input)?;
        crate::sanity::check_image(&next, n, &format!("model after network {iteration}"), "the network made it from a finite residual: a diverging series")?;
        residual = imager.residual_of(&next)?;
        model = next;
        kept_network = iteration;
        let ratio = residual_ratio(&residual, &dirty);
        ratios.push(ratio);
        log::info!("network {iteration} of {total}: residual ratio {ratio:.4e}");
        let reason = config.stop.stop_reason(&ratios, iteration == total, step.early_stop_from());
        match reason {
            Some(reason) if reason.is_rejection() && config.stop.divergence_guard => {
                (kept_network, model, residual) = match best.take() {
                    Some(best) => (best.iteration, best.model, best.residual),
                    None => (0, vec![0.0; n * n], dirty.clone()),
                };
                log::warn!(
                    "the series diverged ({reason:?}, residual ratio {ratio:.4} after network {iteration}); stopped and kept {}. The data are probably outside what the series was trained for",
                    if kept_network == 0 { "the empty model".to_string() } else { format!("the model of network {kept_network}") }
                );
                stop = Some(reason);
                break;
            }
            Some(reason) => {
                log::info!("stopped after network {iteration} ({reason:?}, residual ratio {ratio:.4e})");
                stop = Some(reason);
                break;
            }
            None if config.stop.divergence_guard => {
                if ratio < best.as_ref().map_or(1.0, |b| b.residual_ratio) {
                    best = Some(Iterate { iteration, residual_ratio: ratio, model: model.clone(), residual: residual.clone() });
                }
            }
            None => {}
        }
    }
    let networks_run = ratios.len();
    let rejected = stop.is_some_and(StopReason::is_rejection);
    let (mut final_clean_cycles, mut ratio) = (0, residual_ratio(&residual, &dirty));
    if let Some(params) = &config.final_clean {
        if params.major_cycles > 0 {
            let input = CleanInput { n, dirty: &dirty, psf: &psf, psf_2n: &psf_2n, mask: None };
            // A rejected series' model is not built on: CLEAN alone images the data (as the
            // engine's final CLEAN stage does).
            if rejected {
                (model, residual, kept_network) = (vec![0.0; n * n], dirty.clone(), 0);
                log::warn!("the series' model being rejected, the final CLEAN images the data from the empty model (CLEAN alone)");
            }
            let outcome = final_clean(params, &input, model, residual, &mut |x| imager.residual_of(x), &mut |_, _, _| ())?;
            log::info!(
                "final CLEAN on the residual: {} major cycles kept, components at {} pixels; {} faint islands ({:.3e} Jy) left the model; residual ratio {:.4e}",
                outcome.cycles,
                outcome.components,
                outcome.faint_islands,
                outcome.faint_flux,
                outcome.ratio
            );
            (model, final_clean_cycles, ratio) = (outcome.model, outcome.cycles, outcome.ratio);
        }
    }
    Ok(DrivenOutcome { model, networks_run, kept_network, stop, ratios, final_clean_cycles, ratio })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_doubled_psf_keeps_its_peak_at_the_centre() {
        let n = 4;
        let mut psf = vec![0.0; n * n];
        psf[2 * n + 2] = 1.0;
        psf[0] = 0.5;
        let d = doubled(&psf, n);
        assert_eq!(d[n * 2 * n + n], 1.0);
        assert_eq!(d[(n - 2) * 2 * n + (n - 2)], 0.5);
        assert_eq!(d.iter().sum::<f64>(), 1.5);
    }
}
