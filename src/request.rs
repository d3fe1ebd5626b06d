//! The imaging request: what `r2d2 image`, Python's `image()`, the Stimela cab and
//! [`Engine::image`](crate::Engine::image) take, declared once; and the dirty image's
//! ([`DirtyRequest`]: its grid and MS groups, `r2d2 dirty`'s options).
//!
//! The command line's options are this declaration (clap, flattened into the commands), Python's
//! keyword arguments are parsed by it ([`ImageRequest::from_named`]), and the cab is generated
//! from it ([`cab_inputs`]). Each default is a named constant of the module that owns the
//! quantity; the request only points at it. A value is checked where it is used, with the
//! request's field name in the error; each interface adds its own spelling.

use crate::operator::WTermMode;
use crate::steps::runtime::{BackendChoice, GraphOptimization};
use crate::{Error, Result};
use clap::builder::{PossibleValuesParser, TypedValueParser};
use clap::{ArgAction, Args, FromArgMatches};
use std::path::PathBuf;

/// Pixels per side of the image, by default: the size the shipped series were trained at.
pub const DEFAULT_SIZE: usize = 512;

/// Steps of a native plugin when the request gives no `iterations`.
pub const DEFAULT_PLUGIN_STEPS: usize = 10;

/// The grid an image is made on, and how the samples are weighted and gridded onto it: what
/// every image product shares (`r2d2 dirty` takes only this).
#[derive(Args, Clone, Debug, PartialEq)]
pub struct GridOptions {
    /// Image size in pixels (N x N).
    #[arg(long, default_value_t = DEFAULT_SIZE)]
    pub size: usize,
    /// Super-resolution factor: pixel = 1 / (SR * 2 * max_uv). Default: the series' own (with
    /// a series), else 1.5.
    #[arg(long, conflicts_with = "pixel_arcsec")]
    pub superresolution: Option<f64>,
    /// Pixel size in arcseconds (instead of the super-resolution factor).
    #[arg(long)]
    pub pixel_arcsec: Option<f64>,
    /// The longest baseline (wavelengths) the super-resolution factor is applied to, in place
    /// of the data's own: parts of one observation imaged apart then share one grid.
    #[arg(long)]
    pub longest_baseline: Option<f64>,
    /// natural, uniform, briggs, or given (the imaging weights that come with the data: a
    /// table's `imaging_weight` column, a .mat file's `nWimag`). Default: the series' own
    /// (with a series), else briggs.
    #[arg(long, value_parser = ["natural", "uniform", "briggs", "given"])]
    pub weighting: Option<String>,
    /// Briggs robustness R (implies briggs). Default: the series' own, else 0.
    #[arg(long, allow_hyphen_values = true)]
    pub robust: Option<f64>,
    /// Weighting grid: cells per axis / image size (the uv cuts and tapers are evaluated on
    /// it, as WSClean does on its grid of padding x size cells). Default: 2; a series run at a
    /// size it was not trained for weighs on its trained field's grid (the same uv cell, so the
    /// PSF it was trained on), as WSClean's -super-weight does.
    #[arg(long)]
    pub weighting_grid_factor: Option<f64>,
    /// Leave out baselines shorter than this (wavelengths), as WSClean's -minuv-l.
    #[arg(long, allow_hyphen_values = true)]
    pub minuv_l: Option<f64>,
    /// Leave out baselines longer than this (wavelengths), as WSClean's -maxuv-l (the
    /// super-resolution factor then applies to it, where the data reach it).
    #[arg(long, allow_hyphen_values = true)]
    pub maxuv_l: Option<f64>,
    /// Gaussian taper of the imaging weights whose image-plane FWHM is this (arcsec), as
    /// WSClean's -taper-gaussian.
    #[arg(long, allow_hyphen_values = true)]
    pub taper_gaussian: Option<f64>,
    /// Tukey taper: the weights fall from 1 to 0 over this many wavelengths inside maxuv-l,
    /// as WSClean's -taper-tukey (needs maxuv-l).
    #[arg(long, allow_hyphen_values = true)]
    pub taper_tukey: Option<f64>,
    /// Restoring beam: circular, of this FWHM (arcsec), not fitted to the PSF, as WSClean's
    /// -beam-size.
    #[arg(long, conflicts_with = "beam_shape", allow_hyphen_values = true)]
    pub beam_size: Option<f64>,
    /// Restoring beam: FWHM of the major and minor axes (arcsec) and position angle (degrees
    /// east of north), not fitted to the PSF, as WSClean's -beam-shape.
    #[arg(long, num_args = 3, value_names = ["MAJOR", "MINOR", "PA"], allow_hyphen_values = true, conflicts_with_all = ["circular_beam", "theoretic_beam"])]
    pub beam_shape: Option<Vec<f64>>,
    /// Restoring beam: a circular Gaussian fitted to the PSF's main lobe, as WSClean's
    /// -circular-beam.
    #[arg(long)]
    pub circular_beam: bool,
    /// Restoring beam: not fitted to the PSF; without a beam size or shape, the theoretic beam
    /// (as --theoretic-beam; WSClean 3.1 then restores with none).
    #[arg(long = "no-fit-beam", action = ArgAction::SetFalse)]
    pub fit_beam: bool,
    /// Restoring beam: circular, FWHM 1 / the longest baseline kept (radians), or the
    /// Gaussian taper's FWHM where wider, as WSClean's -theoretic-beam.
    #[arg(long, conflicts_with_all = ["beam_size", "circular_beam"])]
    pub theoretic_beam: bool,
    /// Stokes parameter to image, as WSClean's -pol: only I (from I, XX+YY or RR+LL) is
    /// imaged here.
    #[arg(long, default_value = "I", value_parser = PossibleValuesParser::new(["I"]), ignore_case = true)]
    pub pol: String,
    /// NUFFT accuracy (relative).
    #[arg(long, default_value_t = crate::nufft::DEFAULT_EPSILON)]
    pub epsilon: f64,
    /// NUFFT oversampling factor [default: 2; a residual update through the w-term operator
    /// with its samples held takes the cheaper of 1.5 and 2 for the data].
    #[arg(long)]
    pub oversampling: Option<f64>,
    /// The w-term: auto (corrected by w-gridding where it turns a phase by more than the
    /// accuracy over the field), on, or off (coplanar, for comparison).
    #[arg(long, default_value = "auto", value_parser = PossibleValuesParser::new(["auto", "on", "off"]).try_map(|name| WTermMode::from_name(&name)))]
    pub w_term: WTermMode,
    /// Threads (0: all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

impl GridOptions {
    /// The weighting asked for (`None`: none; `robust` alone means Briggs).
    pub fn weighting(&self) -> Result<Option<crate::Weighting>> {
        crate::Weighting::from_options(self.weighting.as_deref(), self.robust)
    }

    /// The uv cuts and tapers asked for, checked.
    pub fn uv(&self) -> Result<crate::weighting::UvControls> {
        let uv = crate::weighting::UvControls { minuv_l: self.minuv_l, maxuv_l: self.maxuv_l, taper_gaussian: self.taper_gaussian, taper_tukey: self.taper_tukey };
        uv.check()?;
        Ok(uv)
    }

    /// The restoring beam asked for, checked: a given size or shape, else the theoretic beam
    /// where no fit is asked for, else a fit (circular or elliptical).
    pub fn restoring_beam(&self) -> Result<crate::params::RestoringBeam> {
        use crate::params::RestoringBeam;
        let beam = match (self.beam_size, self.beam_shape.as_deref()) {
            (Some(size), _) => ("beam_size", RestoringBeam::Given { major_arcsec: size, minor_arcsec: size, pa_deg: 0.0 }),
            (None, Some(&[major_arcsec, minor_arcsec, pa_deg])) => ("beam_shape", RestoringBeam::Given { major_arcsec, minor_arcsec, pa_deg }),
            (None, Some(other)) => return Err(Error::parameter("beam_shape", format!("expected three numbers, MAJOR MINOR PA, got {}", other.len()))),
            (None, None) if self.theoretic_beam || !self.fit_beam => ("theoretic_beam", RestoringBeam::Theoretic),
            (None, None) if self.circular_beam => ("circular_beam", RestoringBeam::FitCircular),
            (None, None) => ("fit_beam", RestoringBeam::Fit),
        };
        beam.1.check(beam.0)?;
        Ok(beam.1)
    }

    /// A dirty image's parameters: what is not asked for at its default.
    pub fn dirty_params(&self) -> Result<crate::imaging::DirtyParams> {
        use crate::imaging::{DirtyParams, PixelScale, DEFAULT_SUPERRESOLUTION};
        crate::limits::check_image_size(self.size).map_err(|m| Error::parameter("size", m))?;
        crate::limits::check_threads(self.threads).map_err(|m| Error::parameter("threads", m))?;
        Ok(DirtyParams {
            size: self.size,
            pixel: match (self.pixel_arcsec, self.longest_baseline) {
                (Some(p), _) => PixelScale::Arcsec(p),
                (None, None) => PixelScale::SuperResolution(self.superresolution.unwrap_or(DEFAULT_SUPERRESOLUTION)),
                // The pixel the factor gives on the given baseline, whatever the data's own.
                (None, Some(longest)) => {
                    let sr = self.superresolution.unwrap_or(DEFAULT_SUPERRESOLUTION);
                    let geometry = crate::operator::ImageGeometry::from_superresolution(self.size, sr, longest).map_err(|e| Error::parameter("longest_baseline", e.to_string()))?;
                    PixelScale::Arcsec(geometry.pixel_arcsec())
                }
            },
            weighting: self.weighting()?.unwrap_or(crate::weighting::DEFAULT_WEIGHTING),
            grid_factor: self.weighting_grid_factor.unwrap_or(crate::weighting::DEFAULT_GRID_FACTOR),
            nufft: crate::nufft::NufftParams { epsilon: self.epsilon, oversampling: self.oversampling.unwrap_or(crate::nufft::DEFAULT_OVERSAMPLING) },
            w_term: self.w_term,
            threads: self.threads,
            uv: self.uv()?,
        })
    }
}

/// What to read of a MeasurementSet (refused for other inputs).
#[derive(Args, Clone, Debug, PartialEq)]
pub struct MsOptions {
    /// MS input: the complex column to image (as WSClean's -data-column); default: CORRECTED_DATA
    /// when the MS has it, else DATA (as WSClean).
    #[arg(long, default_value = "auto")]
    pub data_column: String,
    /// MS input: field id or name (needed when the MS has several fields).
    #[arg(long)]
    pub field: Option<String>,
    /// MS input: spectral windows, comma separated (default: all).
    #[arg(long, value_delimiter = ',')]
    pub spw: Option<Vec<usize>>,
    /// MS input: channel range START END (END excluded) of every window.
    #[arg(long, num_args = 2, value_names = ["START", "END"])]
    pub channels: Option<Vec<usize>>,
    /// MS input: image N groups of the channels (all windows' channels in order of
    /// frequency, cut into N runs of equal counts) one after another on one grid, as WSClean's
    /// -channels-out: NAME-0000-*.fits, ..., and a cube of each product (NAME-*-cube.fits).
    #[arg(long)]
    pub channels_out: Option<usize>,
    /// MS input, with channels-out: also image the whole band on the same grid, as
    /// NAME-MFS-*.fits (WSClean's -join-channels MFS products).
    #[arg(long, requires = "channels_out")]
    pub join_channels: bool,
}

impl MsOptions {
    /// The first option set away from its default, by name (a non-MS input refuses it).
    pub fn given(&self) -> Option<&'static str> {
        let default = MsOptions::default();
        [
            ("data_column", self.data_column != default.data_column),
            ("field", self.field.is_some()),
            ("spw", self.spw.is_some()),
            ("channels", self.channels.is_some()),
            ("channels_out", self.channels_out.is_some()),
        ]
        .into_iter()
        .find_map(|(name, given)| given.then_some(name))
    }
}

#[cfg(feature = "ms")]
impl MsOptions {
    pub fn selection(&self) -> Result<crate::ms::MsSelection> {
        let channels = match self.channels.as_deref() {
            None => None,
            Some(&[start, end]) => Some([start, end]),
            Some(other) => return Err(Error::parameter("channels", format!("expected two numbers, START and END, got {}", other.len()))),
        };
        Ok(crate::ms::MsSelection {
            data_column: self.data_column.clone(),
            // Any text selects a field (by id or name): its parse cannot fail.
            field: self.field.as_deref().map(|f| match f.parse() {
                Ok(selector) => selector,
                Err(never) => match never {},
            }),
            spw: self.spw.clone(),
            channels,
            channel_group: None,
        })
    }
}

/// The step that improves the model, and its controls.
#[derive(Args, Clone, Debug, PartialEq)]
pub struct StepOptions {
    /// Network step: `auto` (the series trained for the image size, see `r2d2 models`), a model
    /// series (a name from `r2d2 models`, or its directory), `clean` (the built-in Hogbom
    /// CLEAN), or a native plugin library (`.so`, `.dylib`, `.dll`).
    #[arg(long, default_value = crate::steps::series::AUTO_SERIES)]
    pub step: String,
    /// Iterations of the step: CLEAN major cycles (default 20, WSClean's -nmiter), the first networks of a series
    /// (default: all), or the steps of a native plugin (default 10).
    #[arg(long)]
    pub iterations: Option<usize>,
    /// CLEAN (step clean): most components over all major cycles, as WSClean's -niter.
    #[arg(long)]
    pub niter: Option<usize>,
    /// CLEAN: minor-cycle loop gain, as WSClean's -gain (default 0.1).
    #[arg(long)]
    pub gain: Option<f64>,
    /// CLEAN: the fraction of the peak each major cycle cleans away, as WSClean's -mgain (default 0.8; 1: no limit).
    #[arg(long)]
    pub mgain: Option<f64>,
    /// CLEAN: stop at this many times the residual's noise, as WSClean's -auto-threshold
    /// (default 3; 0: none). A series: the depth of its final CLEAN's cycles inside the mask
    /// of what it found (default 2; 1 as WSClean's self-calibration settings: noise inside the
    /// mask becomes model, at a cost in faint-emission precision).
    #[arg(long)]
    pub auto_threshold: Option<f64>,
    /// CLEAN: stop below this residual peak in Jy/beam, as WSClean's -threshold.
    #[arg(long)]
    pub threshold: Option<f64>,
    /// CLEAN: clean without a mask down to this many times the residual's noise, then only
    /// where components were taken, down to auto-threshold, as WSClean's -auto-mask. A
    /// series: keep the model to where the residual, smoothed to the beam or wider, has risen
    /// above this many of its noise sigmas (default 5 on an image more than twice the series'
    /// trained size across, else the level its manifest names, if any; 0: none).
    #[arg(long)]
    pub auto_mask: Option<f64>,
    /// A FITS mask on the image's grid (same size, pixel and centre; further axes of length
    /// 1), as WSClean's -fits-mask: CLEAN takes components only where it is not zero; a
    /// series' model is kept to it after each network, and its final CLEAN cycles clean
    /// inside it.
    #[arg(long)]
    pub fits_mask: Option<PathBuf>,
    /// Configuration of a native plugin, a YAML/JSON mapping (e.g. '{gain: 0.1}').
    #[arg(long)]
    pub plugin_config: Option<String>,
    /// ONNX inference backend for a series: auto (native ONNX Runtime if found), ort, tract.
    #[arg(long, default_value = "auto", value_parser = PossibleValuesParser::new(["auto", "ort", "tract"]).try_map(|name| name.parse::<BackendChoice>()))]
    pub backend: BackendChoice,
    /// Load each network of a series only when it runs, not while the previous one infers
    /// (one network resident instead of two; loading then adds to the wall time).
    #[arg(long = "no-prefetch", action = ArgAction::SetFalse)]
    pub prefetch: bool,
    /// A series' model as the networks leave it: no final CLEAN cycles on its residual (which
    /// otherwise give compact sources the fluxes the data measure).
    #[arg(long = "no-final-clean", action = ArgAction::SetFalse)]
    pub final_clean: bool,
    /// ONNX Runtime graph optimisation: auto (all for small networks, extended for large
    /// ones), extended (least memory) or all (faster inference: weights copied into a blocked
    /// layout, larger activations).
    #[arg(long, default_value = "auto", value_parser = PossibleValuesParser::new(["auto", "extended", "all"]).try_map(|name| name.parse::<GraphOptimization>()))]
    pub graph_optimization: GraphOptimization,
}

impl StepOptions {
    /// Whether the step is a network series (`auto` or a named one), which may load ONNX
    /// Runtime; a step that does not parse is not one (its error comes when it is built).
    pub fn runs_a_series(&self) -> bool {
        matches!(StepChoice::parse(&self.step, None), Ok(StepChoice::Auto | StepChoice::Series(_)))
    }
}

/// The step a request names, parsed.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum StepChoice {
    /// The series trained for the image size (see `r2d2 models`).
    Auto,
    /// The built-in Hogbom CLEAN.
    Clean,
    /// A model series: its directory, or a name `r2d2 models` lists.
    Series(PathBuf),
    /// A native plugin library and its configuration (a YAML/JSON mapping).
    Native { library: PathBuf, config: Option<serde_yaml::Value> },
}

impl StepChoice {
    /// A step as the request names it: `auto`, `clean`, a plugin library (`.so`, `.dylib`,
    /// `.dll`, which alone takes `plugin_config`, a YAML or JSON mapping), or a series (a
    /// directory or a name `r2d2 models` lists).
    pub(crate) fn parse(step: &str, plugin_config: Option<&str>) -> Result<StepChoice> {
        let path = PathBuf::from(step);
        let is_library = matches!(path.extension().and_then(|e| e.to_str()), Some("so" | "dylib" | "dll"));
        if plugin_config.is_some() && !is_library {
            return Err(Error::parameter("plugin_config", format!("only a native plugin takes a configuration; the step is '{step}'")));
        }
        Ok(match step {
            "clean" => StepChoice::Clean,
            crate::steps::series::AUTO_SERIES => StepChoice::Auto,
            _ if is_library => StepChoice::Native {
                library: path,
                config: plugin_config
                    .map(|text| serde_yaml::from_str(text).map_err(|e| Error::parameter("plugin_config", format!("expected a YAML or JSON mapping: {e}"))))
                    .transpose()?,
            },
            _ => StepChoice::Series(path),
        })
    }
}

/// One observation's imaging: the grid, what to read, the step, and where the products go.
#[derive(Args, Clone, Debug, PartialEq)]
pub struct ImageRequest {
    #[command(flatten)]
    pub grid: GridOptions,
    #[command(flatten)]
    pub ms: MsOptions,
    #[command(flatten)]
    pub step: StepOptions,
    /// MS input: predict the final model's visibilities into this column of the MS (e.g.
    /// MODEL_DATA; created when missing).
    #[arg(long)]
    pub model_column: Option<String>,
    /// Also write NAME-pb.fits, the telescope's published primary beam at the observation's
    /// centre frequency about the phase centre (the VLA's of EVLA Memo 195; MeerKAT's L band of
    /// Mauch et al. 2020), and NAME-image-pb.fits and NAME-model-pb.fits divided by it, blank
    /// where it is below primary_beam_limit, as WSClean's -apply-primary-beam.
    #[arg(long)]
    pub apply_primary_beam: bool,
    /// The beam level below which the primary-beam corrected images are blank (NaN), as
    /// WSClean's -primary-beam-limit (whose own default is lower, for EveryBeam's beams).
    #[arg(long, default_value_t = crate::primary_beam::DEFAULT_LIMIT)]
    pub primary_beam_limit: f64,
    /// Ground truth (FITS) for SNR/logSNR per iteration.
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// Output prefix (WSClean's -name): the products are written as NAME-model.fits, ...
    /// (`{job}` stands for the job's id). `r2d2 image` writes at `r2d2` when none is given;
    /// from Python or the library, nothing is written unless one is given.
    #[arg(long)]
    pub name: Option<String>,
    /// Most memory (MB) the samples may take held in memory where the residual update needs
    /// them (the w-term); above it they are read again at each update (or only for the kernels
    /// and the final residual where a Taylor series in w replaces the operator).
    #[arg(long, default_value_t = crate::params::DEFAULT_HOLD_MB)]
    pub hold_mb: f64,
    /// Most memory (MB) the kernels of the w-term's convolution forms of the residual update
    /// may take (the w-aware Toeplitz form while gridding, unless the samples held would take
    /// more; the Taylor series in w); beyond it the update runs through the operator.
    #[arg(long, default_value_t = crate::params::DEFAULT_KERNEL_MB)]
    pub kernel_mb: f64,
}

/// One observation's dirty image and PSF (what `r2d2 dirty` and
/// [`Engine::dirty`](crate::Engine::dirty) take): the grid, what to read, and where they go.
#[derive(Args, Clone, Debug, Default, PartialEq)]
pub struct DirtyRequest {
    #[command(flatten)]
    pub grid: GridOptions,
    #[command(flatten)]
    pub ms: MsOptions,
    /// Output prefix (WSClean's -name): writes NAME-dirty.fits and NAME-psf.fits. `r2d2 dirty`
    /// writes at `r2d2` when none is given; from the library, nothing is written unless one is.
    #[arg(long)]
    pub name: Option<String>,
}

impl Default for ImageRequest {
    /// Every option at its default: the declaration parsed from no arguments.
    fn default() -> Self {
        ImageRequest::from_named(std::iter::empty()).expect("every option of the request has a default or is optional")
    }
}

impl Default for GridOptions {
    fn default() -> Self {
        ImageRequest::default().grid
    }
}

impl Default for StepOptions {
    fn default() -> Self {
        ImageRequest::default().step
    }
}

impl Default for MsOptions {
    fn default() -> Self {
        ImageRequest::default().ms
    }
}

/// A value given by name ([`ImageRequest::from_named`]): a switch, or the words of an option's
/// value (one for most, two for `channels`, any number for `spw`).
#[derive(Clone, Debug, PartialEq)]
pub enum NamedValue {
    Switch(bool),
    Words(Vec<String>),
}

impl ImageRequest {
    /// The declaration as a clap command of its own (to list, document or parse the options).
    pub fn command() -> clap::Command {
        let mut command = ImageRequest::augment_args(clap::Command::new("image").no_binary_name(true));
        // Built, so that each option can be shown as clap shows it (in errors).
        command.build();
        command
    }

    /// The names the request's options have (its fields' names, as Python's keyword arguments
    /// and the cab spell them).
    pub fn option_names() -> Vec<String> {
        options(&ImageRequest::command()).map(|a| a.get_id().to_string()).collect()
    }

    /// A request from options given by name (Python's keyword arguments): each is checked as
    /// the command line checks it, and an error names the option as it was given.
    pub fn from_named(named: impl IntoIterator<Item = (String, NamedValue)>) -> Result<ImageRequest> {
        let command = ImageRequest::command();
        let mut words: Vec<String> = Vec::new();
        for (name, value) in named {
            let Some(arg) = options(&command).find(|a| a.get_id() == name.as_str()) else {
                let mut known = ImageRequest::option_names();
                known.sort();
                return Err(Error::parameter(name, format!("not an option of the request; the options: {}", known.join(", "))));
            };
            let long = format!("--{}", arg.get_long().expect("every option of the request is named"));
            let switch = matches!(arg.get_action(), ArgAction::SetTrue | ArgAction::SetFalse);
            match (value, switch) {
                // A switch says what it turns: `final_clean: false` is `--no-final-clean`.
                (NamedValue::Switch(on), true) => {
                    if on == matches!(arg.get_action(), ArgAction::SetTrue) {
                        words.push(long);
                    }
                }
                (NamedValue::Words(given), false) => {
                    words.push(long);
                    // A list for an option whose values are one delimited word (`spw`).
                    match arg.get_value_delimiter() {
                        Some(delimiter) => words.push(given.join(&delimiter.to_string())),
                        None => words.extend(given),
                    }
                }
                (NamedValue::Switch(on), false) => return Err(Error::parameter(name, format!("expected a value, got the switch {on}"))),
                (NamedValue::Words(given), true) => return Err(Error::parameter(name, format!("expected true or false, got {}", given.join(" ")))),
            }
        }
        let matches = command.clone().try_get_matches_from(&words).map_err(|e| named_error(&command, e))?;
        ImageRequest::from_arg_matches(&matches).map_err(|e| named_error(&command, e))
    }
}

/// The request's options: the command's arguments but clap's own (`--help`).
fn options(command: &clap::Command) -> impl Iterator<Item = &clap::Arg> {
    command.get_arguments().filter(|a| !matches!(a.get_action(), ArgAction::Help | ArgAction::HelpShort | ArgAction::HelpLong | ArgAction::Version))
}

/// A clap error with each option named as the request names it (`size`, not `--size <SIZE>`),
/// keyed by the first option it names.
fn named_error(command: &clap::Command, error: clap::Error) -> Error {
    let text = error.to_string();
    let text = text.trim_start_matches("error: ").split("\n\n").next().unwrap_or("").trim().to_string();
    let mut field = String::from("request");
    let mut first = usize::MAX;
    let mut named = text.clone();
    for arg in command.get_arguments() {
        let id = arg.get_id().to_string();
        let shown = format!("'{arg}'");
        if let Some(at) = text.find(&shown) {
            if at < first {
                (first, field) = (at, id.clone());
            }
            named = named.replace(&shown, &format!("'{id}'"));
        }
    }
    Error::parameter(field, named)
}

/// The Stimela cab's inputs for the request's options, in the cab's YAML (a mapping from each
/// option's name to its `info`, `dtype` or `choices`, and `policies`): the
/// `r2d2-image` cab's inputs are these, so that a new option reaches recipes without a second
/// declaration. An input is named as its command-line option (the cab turns `_` into `-`):
/// a switch by what it does (`no_final_clean`).
#[cfg(test)]
pub(crate) fn cab_inputs() -> serde_yaml::Mapping {
    use serde_yaml::Value;
    let mut inputs = serde_yaml::Mapping::new();
    let command = ImageRequest::command();
    for arg in options(&command) {
        let mut input = serde_yaml::Mapping::new();
        let mut info = arg.get_help().map(|h| h.to_string()).unwrap_or_default().split_whitespace().collect::<Vec<_>>().join(" ");
        // Said, not set: the cab passes nothing where a recipe gives nothing, and the command
        // line's default applies (one default, in one place).
        if let [default] = arg.get_default_values() {
            if !matches!(arg.get_action(), ArgAction::SetTrue | ArgAction::SetFalse) {
                info = format!("{info} [default: {}]", default.to_string_lossy());
            }
        }
        input.insert("info".into(), info.into());
        let choices: Vec<Value> = arg.get_possible_values().iter().map(|v| Value::from(v.get_name())).collect();
        let parser = arg.get_value_parser().type_id();
        let several = arg.get_num_args().is_some_and(|n| n.max_values() > 1);
        let delimited = arg.get_value_delimiter();
        let dtype = if matches!(arg.get_action(), ArgAction::SetTrue | ArgAction::SetFalse) {
            Some("bool")
        } else if !choices.is_empty() {
            None
        } else if parser == std::any::TypeId::of::<usize>() {
            Some(if several || delimited.is_some() { "List[int]" } else { "int" })
        } else if parser == std::any::TypeId::of::<f64>() {
            Some(if several { "List[float]" } else { "float" })
        } else if parser == std::any::TypeId::of::<PathBuf>() {
            Some("File")
        } else {
            Some("str")
        };
        match dtype {
            Some(dtype) => input.insert("dtype".into(), dtype.into()),
            None => input.insert("choices".into(), Value::Sequence(choices)),
        };
        // A list goes on the command line as the option takes it: words, or one delimited word.
        if let Some(delimiter) = delimited {
            input.insert("policies".into(), serde_yaml::from_str(&format!("{{repeat: '{delimiter}'}}")).unwrap_or_default());
        } else if several {
            input.insert("policies".into(), serde_yaml::from_str("{repeat: list}").unwrap_or_default());
        }
        // The cab's outputs are named from it.
        if arg.get_id() == "name" {
            input.insert("required".into(), true.into());
        }
        let long = arg.get_long().unwrap_or(arg.get_id().as_str());
        inputs.insert(long.replace('-', "_").into(), Value::Mapping(input));
    }
    inputs
}

/// [`cab_inputs`] as YAML text that Stimela reads as it is meant: a word YAML 1.1 takes for a
/// boolean (`on`, `off`), as the cab's reader does, is quoted.
#[cfg(test)]
pub(crate) fn cab_inputs_yaml() -> String {
    let text = serde_yaml::to_string(&cab_inputs()).unwrap_or_default();
    text.lines()
        .map(|line| {
            let word = line.trim_start().strip_prefix("- ").unwrap_or("");
            let boolean = ["on", "off", "yes", "no", "y", "n", "true", "false"].contains(&word.to_ascii_lowercase().as_str());
            if boolean { format!("{}'{word}'\n", &line[..line.len() - word.len()]) } else { format!("{line}\n") }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn words(word: &str) -> NamedValue {
        NamedValue::Words(word.split(' ').map(str::to_string).collect())
    }

    #[test]
    fn the_defaults_are_the_named_constants() {
        let r = ImageRequest::default();
        assert_eq!(r.grid.size, DEFAULT_SIZE);
        assert_eq!(r.grid.epsilon, crate::nufft::DEFAULT_EPSILON);
        assert_eq!(r.grid.oversampling, None);
        assert_eq!(r.grid.weighting_grid_factor, None);
        assert_eq!(r.hold_mb, crate::params::DEFAULT_HOLD_MB);
        assert_eq!(r.kernel_mb, crate::params::DEFAULT_KERNEL_MB);
        assert_eq!((r.grid.superresolution, r.grid.weighting.as_deref(), r.name.as_deref()), (None, None, None));
        assert_eq!((r.step.step.as_str(), r.step.prefetch, r.step.final_clean), (crate::steps::series::AUTO_SERIES, true, true));
        assert_eq!((r.grid.w_term, r.step.backend, r.step.graph_optimization), (WTermMode::Auto, BackendChoice::Auto, GraphOptimization::Auto));
        assert_eq!((r.apply_primary_beam, r.primary_beam_limit), (false, crate::primary_beam::DEFAULT_LIMIT));
    }

    #[test]
    fn options_given_by_name_are_parsed_as_the_command_line_parses_them() {
        let r = ImageRequest::from_named([
            ("size".to_string(), words("128")),
            ("final_clean".to_string(), NamedValue::Switch(false)),
            ("prefetch".to_string(), NamedValue::Switch(true)),
            ("channels".to_string(), words("2 6")),
            ("spw".to_string(), words("0 1")),
            ("robust".to_string(), words("-0.5")),
            ("w_term".to_string(), words("off")),
            ("minuv_l".to_string(), words("100")),
            ("maxuv_l".to_string(), words("2e5")),
            ("taper_gaussian".to_string(), words("1.5")),
            ("taper_tukey".to_string(), words("5000")),
            ("beam_shape".to_string(), words("10 5 -30")),
            ("apply_primary_beam".to_string(), NamedValue::Switch(true)),
            ("primary_beam_limit".to_string(), words("0.2")),
        ])
        .unwrap();
        assert_eq!(r.grid.restoring_beam().unwrap(), crate::params::RestoringBeam::Given { major_arcsec: 10.0, minor_arcsec: 5.0, pa_deg: -30.0 });
        assert_eq!((r.apply_primary_beam, r.primary_beam_limit), (true, 0.2));
        assert_eq!(r.grid.uv().unwrap(), crate::weighting::UvControls { minuv_l: Some(100.0), maxuv_l: Some(2e5), taper_gaussian: Some(1.5), taper_tukey: Some(5000.0) });
        assert_eq!((r.grid.size, r.step.final_clean, r.step.prefetch), (128, false, true));
        assert_eq!((r.ms.channels, r.ms.spw, r.grid.robust, r.grid.w_term), (Some(vec![2, 6]), Some(vec![0, 1]), Some(-0.5), WTermMode::Off));
    }

    #[test]
    fn a_bad_option_given_by_name_is_named_as_given() {
        let error = |options: Vec<(&str, NamedValue)>| ImageRequest::from_named(options.into_iter().map(|(n, v)| (n.to_string(), v))).unwrap_err().to_string();
        let e = error(vec![("size", words("big"))]);
        assert!(e.contains("'size'") && e.contains("big") && !e.contains("--size"), "{e}");
        let e = error(vec![("weighting", words("brigs"))]);
        assert!(e.contains("'weighting'") && e.contains("briggs"), "{e}");
        let e = error(vec![("superresolution", words("2")), ("pixel_arcsec", words("1"))]);
        assert!(e.contains("'superresolution'") && e.contains("'pixel_arcsec'") && !e.contains("--"), "{e}");
        let e = error(vec![("sise", words("12"))]);
        assert!(e.contains("sise") && e.contains("size"), "{e}");
        let e = error(vec![("final_clean", words("no"))]);
        assert!(e.contains("final_clean") && e.contains("true or false"), "{e}");
        let e = error(vec![("pol", words("IQUV"))]);
        assert!(e.contains("'pol'") && e.contains("IQUV") && e.contains('I'), "{e}");
        assert!(ImageRequest::from_named([("pol".to_string(), words("i"))]).is_ok());
        let e = error(vec![("backend", words("onnx"))]);
        assert!(e.contains("'backend'") && e.contains("tract"), "{e}");
        // The restoring beam: the widths checked, naming the option; the choices combined as
        // WSClean combines them.
        use crate::params::RestoringBeam;
        let beam = |options: Vec<(&str, NamedValue)>| ImageRequest::from_named(options.into_iter().map(|(n, v)| (n.to_string(), v))).and_then(|r| r.grid.restoring_beam());
        let e = beam(vec![("beam_shape", words("5 10 0"))]).unwrap_err().to_string();
        assert!(e.contains("beam_shape") && e.contains("major axis first"), "{e}");
        let e = beam(vec![("beam_size", words("-3"))]).unwrap_err().to_string();
        assert!(e.contains("beam_size") && e.contains("positive"), "{e}");
        let e = beam(vec![("beam_shape", words("5 3"))]).unwrap_err().to_string();
        assert!(e.contains("beam_shape") && e.contains('3'), "{e}");
        let e = beam(vec![("beam_size", words("3")), ("beam_shape", words("5 3 0"))]).unwrap_err().to_string();
        assert!(e.contains("'beam_size'") && e.contains("'beam_shape'"), "{e}");
        assert_eq!(beam(vec![]).unwrap(), RestoringBeam::Fit);
        assert_eq!(beam(vec![("circular_beam", NamedValue::Switch(true))]).unwrap(), RestoringBeam::FitCircular);
        assert_eq!(beam(vec![("fit_beam", NamedValue::Switch(false))]).unwrap(), RestoringBeam::Theoretic);
        assert_eq!(beam(vec![("theoretic_beam", NamedValue::Switch(true))]).unwrap(), RestoringBeam::Theoretic);
        assert_eq!(beam(vec![("beam_size", words("4")), ("fit_beam", NamedValue::Switch(false))]).unwrap(), RestoringBeam::Given { major_arcsec: 4.0, minor_arcsec: 4.0, pa_deg: 0.0 });
        // A negative length is a value (checked where it is used, naming the field).
        let r = ImageRequest::from_named([("minuv_l".to_string(), words("-5"))]).unwrap();
        let e = r.grid.uv().unwrap_err().to_string();
        assert!(e.contains("minuv_l") && e.contains("-5") && !e.contains("--"), "{e}");
    }

    #[test]
    fn the_cab_has_every_option_with_its_type() {
        let inputs = cab_inputs();
        assert_eq!(inputs.len(), ImageRequest::option_names().len());
        let get = |name: &str, key: &str| inputs[name][key].clone();
        assert_eq!(get("size", "dtype"), "int");
        assert!(get("size", "info").as_str().unwrap().ends_with(&format!("[default: {DEFAULT_SIZE}]")));
        assert_eq!(get("epsilon", "dtype"), "float");
        assert_eq!(get("truth", "dtype"), "File");
        assert_eq!(get("no_final_clean", "dtype"), "bool");
        assert_eq!((get("apply_primary_beam", "dtype"), get("primary_beam_limit", "dtype")), ("bool".into(), "float".into()));
        assert_eq!(get("channels", "dtype"), "List[int]");
        assert_eq!(get("beam_shape", "dtype"), "List[float]");
        assert_eq!(get("no_fit_beam", "dtype"), "bool");
        assert_eq!(get("spw", "policies")["repeat"], ",");
        assert_eq!(get("backend", "choices"), serde_yaml::from_str::<serde_yaml::Value>("[auto, ort, tract]").unwrap());
    }

    /// The `r2d2-image` cab the Python package ships has the request's options as its inputs
    /// (beside the observation): regenerated between its markers by
    /// `R2D2_UPDATE_CAB=1 cargo test --release --lib packaged_image_cab`.
    #[test]
    fn the_packaged_image_cab_is_generated_from_the_request() {
        const BEGIN: &str = "      # Generated from the request (src/request.rs, cab_inputs): do not edit.\n";
        const END: &str = "      # End of the generated inputs.\n";
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("python/r2d2_imaging/r2d2.yml");
        let text = std::fs::read_to_string(&path).unwrap();
        let (Some(begin), Some(end)) = (text.find(BEGIN), text.find(END)) else { panic!("{}: no generated block", path.display()) };
        let generated: String = cab_inputs_yaml().lines().map(|l| format!("      {l}\n")).collect();
        let updated = format!("{}{BEGIN}{generated}{}", &text[..begin], &text[end..]);
        if std::env::var_os("R2D2_UPDATE_CAB").is_some() {
            std::fs::write(&path, &updated).unwrap();
            return;
        }
        assert!(updated == text, "{}: the r2d2-image cab's inputs differ from the request's; R2D2_UPDATE_CAB=1 cargo test --release --lib packaged_image_cab", path.display());
        // The generated block is the cab's inputs, beside the observation, in the YAML read back.
        let cabs: serde_yaml::Value = serde_yaml::from_str(&text).unwrap();
        let inputs = cabs["cabs"]["r2d2-image"]["inputs"].as_mapping().unwrap();
        assert_eq!(inputs.len(), cab_inputs().len() + 1);
        assert!(inputs.contains_key("obs"));
        assert_eq!(inputs["w_term"]["choices"], serde_yaml::from_str::<serde_yaml::Value>("['auto', 'on', 'off']").unwrap());
    }
}
