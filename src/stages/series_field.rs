//! Which network series a pipeline's jobs go on to, as the stages before the step need to know
//! it at build time (the weighting stage weighs on a series' trained field's grid); the step
//! resolves its series the same way.

use crate::job::{BuildContext, ImageContext};
use crate::steps::onnx::OnnxConfig;
use crate::steps::series::{ImagingSetup, Series};
use crate::Result;

/// The series a weighting stage's jobs go on to, with its trained image size nearest the
/// image's, where that is not the image's size: the `kind: onnx` stages after it (all on one
/// trained size), each series resolved as its step resolves it. `None` where none runs off
/// its size or a series does not resolve (its step says why).
pub(super) fn series_field_off_size(ctx: &BuildContext<'_>, scheme: &str, robust: f64) -> Result<Option<(String, usize)>> {
    let image = ctx.image();
    let mut fields = Vec::new();
    for config in ctx.downstream_params::<OnnxConfig>()? {
        let choosing = config.series.as_os_str() == crate::steps::series::AUTO_SERIES;
        let setup = ImagingSetup {
            superresolution: image.pixel_arcsec.is_none().then(|| image.superresolution.unwrap_or(crate::imaging::DEFAULT_SUPERRESOLUTION)),
            weighting: Some(scheme.to_string()),
            robust: Some(robust),
            telescope: if choosing { source_telescope(ctx)? } else { None },
            track_hours: None,
            integration_s: None,
        };
        let dir = match choosing {
            true => crate::steps::series::select_for(image.size, &setup).ok().map(|(dir, _)| dir),
            false => crate::steps::series::resolve(&config.series).ok(),
        };
        let Some(series) = dir.and_then(|d| Series::open(&d).ok()) else { return Ok(None) };
        fields.push((series.name.clone(), series.nearest_trained_size(image.size)));
    }
    fields.dedup_by_key(|(_, trained)| *trained);
    Ok(match fields.as_slice() {
        [(name, Some(trained))] if *trained != image.size => Some((name.clone(), *trained)),
        _ => None,
    })
}

/// The telescope of the sources before the step (`auto` prefers a series trained for it): the
/// first that says one, in file order (a simulation names its own; a file source's first file
/// says, read without its samples); none where none says.
pub(super) fn source_telescope(ctx: &BuildContext<'_>) -> Result<Option<String>> {
    for (_, source) in ctx.upstream_sources()? {
        if let Some(telescope) = source.telescope()? {
            return Ok(Some(telescope));
        }
    }
    Ok(None)
}
