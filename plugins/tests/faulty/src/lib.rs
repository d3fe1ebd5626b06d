//! A plugin that misbehaves on request, for the host's error-handling tests:
//! `config: {fail: <where>}` with `<where>` one of `create_error`, `create_panic`,
//! `step_error`, `step_panic`, `nan` (a NaN increment at pixel (1, 0)), `huge` (1e300 there), `unwritten` (leaves
//! pixel 0 unwritten) or `none` (a zero increment), at iteration `at` (default 1); and, to
//! test process isolation, `segfault`, `abort`, `exit` (exit status 0) and `hang` (sleeps
//! forever) in the step.

use r2d2_plugin::{export_plugin, Plugin, Setup, StepInput};
use serde::Deserialize;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Config {
    fail: String,
    #[serde(default = "first")]
    at: usize,
}

fn first() -> usize {
    1
}

pub struct Faulty {
    config: Config,
}

impl Plugin for Faulty {
    fn create(config_json: &str, setup: &Setup) -> Result<Self, String> {
        let config: Config = serde_json::from_str(config_json).map_err(|e| format!("config: {e}"))?;
        match config.fail.as_str() {
            "create_error" => Err(format!("refusing to run at image size {} as asked", setup.image_size)),
            "create_panic" => panic!("create panicked as asked"),
            _ => Ok(Faulty { config }),
        }
    }

    fn step(&mut self, input: &StepInput<'_>, increment: &mut [f64]) -> Result<(), String> {
        let failing = input.iteration == self.config.at;
        match self.config.fail.as_str() {
            "step_error" if failing => return Err(format!("step {} failed as asked", input.iteration)),
            "step_panic" if failing => panic!("step {} panicked as asked", input.iteration),
            "segfault" if failing => {
                // SAFETY: none: this plugin exists to crash its process the way a buggy
                // native plugin does; a volatile write to address 0 is not optimised away.
                unsafe { std::ptr::null_mut::<u8>().write_volatile(1) };
            }
            "abort" if failing => std::process::abort(),
            "exit" if failing => std::process::exit(0),
            "hang" if failing => loop {
                std::thread::sleep(std::time::Duration::from_secs(3600));
            },
            _ => {}
        }
        match self.config.fail.as_str() {
            "huge" if failing => {
                increment.fill(0.0);
                increment[1] = 1e300;
            }
            "nan" if failing => {
                increment.fill(0.0);
                increment[1] = f64::NAN;
            }
            // Whatever the host left in pixel 0 stays there.
            "unwritten" if failing => increment[1..].fill(0.0),
            _ => increment.fill(0.0),
        }
        Ok(())
    }
}

export_plugin!(Faulty);
