//! Example native plugin: projected Landweber iterations. The increment is `gain * r_{i-1}`,
//! so with the host's positivity the loop runs `x_i = max(0, x_{i-1} + gain (x_d - D x_{i-1}))`,
//! gradient descent on `||y - Phi x||^2 / 2` projected on the positive orthant. It converges
//! for `0 < gain < 2 / ||D||`.
//!
//! ```yaml
//! step: {kind: native, library: target/release/libr2d2_landweber.so, iterations: 20, config: {gain: 1.0}, to: update}
//! ```

use r2d2_plugin::{export_plugin, Plugin, Setup, StepInput};
use serde::Deserialize;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Config {
    /// Step size, in units of the PSF-normalised data fidelity (D has peak PSF value 1).
    gain: f64,
}

pub struct Landweber {
    gain: f64,
}

impl Plugin for Landweber {
    fn create(config_json: &str, _setup: &Setup) -> Result<Self, String> {
        let config: Config = serde_json::from_str(config_json).map_err(|e| format!("config: {e} (expected {{gain: <positive number>}})"))?;
        if !(config.gain.is_finite() && config.gain > 0.0) {
            return Err(format!("config.gain: expected a positive finite step size, got {}", config.gain));
        }
        Ok(Landweber { gain: config.gain })
    }

    fn step(&mut self, input: &StepInput<'_>, increment: &mut [f64]) -> Result<(), String> {
        for (d, r) in increment.iter_mut().zip(input.residual) {
            *d = self.gain * r;
        }
        Ok(())
    }
}

export_plugin!(Landweber);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_is_checked() {
        let setup = Setup { image_size: 8, iterations: 2 };
        assert!(Landweber::create(r#"{"gain": 0.5}"#, &setup).is_ok());
        for (bad, expect) in [(r#"{}"#, "missing field `gain`"), (r#"{"gain": -1}"#, "positive"), (r#"{"gain": 1, "gian": 2}"#, "unknown field `gian`")] {
            let err = Landweber::create(bad, &setup).err().expect(bad);
            assert!(err.contains(expect), "{bad}: {err}");
        }
    }
}
