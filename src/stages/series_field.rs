//! Which network series a pipeline's jobs go on to, as the stages before the step need to know
//! it at build time (the weighting stage weighs on a series' trained field's grid); the step
//! resolves its series the same way.

use crate::job::{BuildContext, ImageContext};
use crate::steps::onnx::OnnxConfig;
use crate::steps::series::{ImagingSetup, Series};
use crate::Result;

/// The series a weighting stage's jobs go on to, with its trained image size nearest the
/// image's, where that is not the image's size: the `kind: onnx` stages after it (all on one
/// trained size), each series resolved as its step resolves it, with the stage's `weighting`
/// (scheme, robust). `None` where none runs off its size or a series does not resolve (its
/// step says why).
pub(super) fn series_field_off_size(ctx: &BuildContext<'_>, weighting: (&str, f64)) -> Result<Option<(String, usize)>> {
    let size = ctx.image().size;
    let mut fields = Vec::new();
    for config in ctx.downstream_params::<OnnxConfig>()? {
        let setup = imaging_setup(ctx, Some(weighting), config.series.as_os_str() == crate::steps::series::AUTO_SERIES)?;
        let dir = crate::steps::series::choose_for(&config.series, size, &setup).ok().map(|(dir, _)| dir);
        let Some(series) = dir.and_then(|d| Series::open(&d).ok()) else { return Ok(None) };
        fields.push((series.name.clone(), series.nearest_trained_size(size)));
    }
    fields.dedup_by_key(|(_, trained)| *trained);
    Ok(match fields.as_slice() {
        [(name, Some(trained))] if *trained != size => Some((name.clone(), *trained)),
        _ => None,
    })
}

/// The jobs' imaging as a series' validity sees it: the super-resolution (unknown when the
/// pixel size is given in arcsec: it then depends on each job's longest baseline) and the
/// `weighting` (scheme, robust; unknown: `None`).
/// The telescope is looked up only for `auto` (`choosing`), whose choice it takes part in; a
/// named series meets each job's telescope at the job.
pub(super) fn imaging_setup(ctx: &BuildContext<'_>, weighting: Option<(&str, f64)>, choosing: bool) -> Result<ImagingSetup> {
    let image = ctx.image();
    Ok(ImagingSetup {
        superresolution: image.pixel_arcsec.is_none().then(|| image.superresolution.unwrap_or(crate::imaging::DEFAULT_SUPERRESOLUTION)),
        weighting: weighting.map(|(scheme, _)| scheme.to_string()),
        robust: weighting.map(|(_, robust)| robust),
        telescope: if choosing { source_telescope(ctx)? } else { None },
        // Known once the data are read: each job's are checked at its first step.
        track_hours: None,
        integration_s: None,
    })
}

/// The telescope of the sources before the step (`auto` prefers a series trained for it): the
/// first that says one, in file order (a simulation names its own; a file source's first file
/// says, read without its samples); none where none says.
fn source_telescope(ctx: &BuildContext<'_>) -> Result<Option<String>> {
    for (_, source) in ctx.upstream_sources()? {
        if let Some(telescope) = source.telescope()? {
            return Ok(Some(telescope));
        }
    }
    Ok(None)
}
