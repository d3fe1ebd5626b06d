//! WSClean's spelling of the options `r2d2 image` and `r2d2 dirty` share with it, read before
//! the command line is parsed: an option with the same meaning is rewritten to this engine's
//! (`-size 512 512` to `--size 512`), and one without a counterpart here is an error that names
//! what to use instead, rather than clap's "unexpected argument" blaming the input path.

/// How a WSClean option maps onto this engine's.
enum Spelling {
    /// The same meaning: rewritten.
    Same,
    /// No counterpart here: the error's advice.
    Counterpart(&'static str),
}

/// WSClean's options this engine knows of, and how many values each takes.
const OPTIONS: &[(&str, usize, Spelling)] = &[
    ("size", 2, Spelling::Same),
    ("scale", 1, Spelling::Same),
    ("weight", 1, Spelling::Same),
    ("data-column", 1, Spelling::Same),
    ("name", 1, Spelling::Same),
    ("j", 1, Spelling::Same),
    ("niter", 1, Spelling::Same),
    ("auto-threshold", 1, Spelling::Same),
    ("threshold", 1, Spelling::Same),
    ("mgain", 1, Spelling::Same),
    ("gain", 1, Spelling::Same),
    ("minuv-l", 1, Spelling::Same),
    ("maxuv-l", 1, Spelling::Same),
    ("taper-gaussian", 1, Spelling::Same),
    ("taper-tukey", 1, Spelling::Same),
    ("pol", 1, Spelling::Same),
    ("channels-out", 1, Spelling::Same),
    ("channel-range", 2, Spelling::Same),
    ("join-channels", 0, Spelling::Same),
    ("beam-size", 1, Spelling::Same),
    ("beam-shape", 3, Spelling::Same),
    ("circular-beam", 0, Spelling::Same),
    ("elliptical-beam", 0, Spelling::Same),
    ("fit-beam", 0, Spelling::Same),
    ("no-fit-beam", 0, Spelling::Same),
    ("theoretic-beam", 0, Spelling::Same),
    ("beam-fitting-size", 1, Spelling::Counterpart("the beam is fitted to the PSF's main lobe (the pixels above 0.35 of its peak), with no fitting box to size")),
    ("apply-primary-beam", 0, Spelling::Same),
    ("primary-beam-limit", 1, Spelling::Same),
    ("auto-mask", 1, Spelling::Same),
    ("fits-mask", 1, Spelling::Same),
    ("multiscale", 0, Spelling::Counterpart("there is no multiscale CLEAN here; a network series images extended emission itself (the default step)")),
    ("padding", 1, Spelling::Counterpart("the gridder's padding is fixed by --oversampling (default 2, as -padding 2)")),
];

/// WSClean's CLEAN controls, which `r2d2 image --step clean` takes with the same meanings (the
/// masks also with a network series).
const CLEAN_OPTIONS: [&str; 7] = ["niter", "auto-threshold", "threshold", "mgain", "gain", "auto-mask", "fits-mask"];

/// WSClean's primary-beam options, which `r2d2 image` takes and `r2d2 dirty` (the dirty image
/// and the PSF only) refuses.
const PRIMARY_BEAM_OPTIONS: [&str; 2] = ["apply-primary-beam", "primary-beam-limit"];

/// `args` (the whole command line) with WSClean's spellings rewritten, for `image` and `dirty`
/// only; `Err` names the option and its counterpart.
pub fn rewrite(args: Vec<String>) -> Result<Vec<String>, String> {
    let command = match args.iter().skip(1).find(|a| !a.starts_with('-')) {
        Some(c) if c == "image" || c == "dirty" => c.clone(),
        _ => return Ok(args),
    };
    let mut out = Vec::with_capacity(args.len());
    let mut rest = args.into_iter().peekable();
    while let Some(arg) = rest.next() {
        // After `--` every word is an input, whatever it looks like.
        if arg == "--" {
            out.push(arg);
            out.extend(rest);
            break;
        }
        // `--size N N`: WSClean's two numbers with this engine's dashes.
        if arg == "--size" {
            let n = rest.next().ok_or("--size: expected the image size in pixels")?;
            if rest.peek().is_some_and(|m| m.parse::<usize>().is_ok()) {
                let m = rest.next().unwrap_or_default();
                if m != n {
                    return Err(format!("--size {n} {m}: images here are square: give one size (--size {n})"));
                }
            }
            out.extend(["--size".to_string(), n]);
            continue;
        }
        let Some(word) = arg.strip_prefix('-').filter(|n| !n.starts_with('-') && !is_short_flags(n) && !is_number(&arg)) else {
            out.push(arg);
            continue;
        };
        // `-threshold=0.1`: the first value joined to the name.
        let (name, joined) = match word.split_once('=') {
            Some((name, value)) => (name, Some(value.to_string())),
            None => (word, None),
        };
        let Some((_, count, spelling)) = OPTIONS.iter().find(|(o, _, _)| *o == name) else {
            // Clap would take `-channels-out` for the short flags -c, -h, ... and blame `-c`.
            let taken: Vec<String> = OPTIONS.iter().filter(|(_, _, s)| matches!(s, Spelling::Same)).map(|(o, _, _)| format!("-{o}")).collect();
            return Err(format!(
                "-{name}: not supported by r2d2 {command} (not one of the WSClean options it takes: {}); r2d2 {command} --help lists its own options, with two dashes",
                taken.join(", ")
            ));
        };
        if joined.is_some() && *count == 0 {
            return Err(format!("{arg}: -{name} takes no value"));
        }
        let mut values: Vec<String> = joined.into_iter().collect();
        while values.len() < *count {
            let value = rest.next().ok_or_else(|| format!("-{name}: expected {count} value(s), as in WSClean"))?;
            if value.starts_with('-') && !is_number(&value) && !is_angle(&value) {
                let got: Vec<&str> = values.iter().map(String::as_str).chain([value.as_str()]).collect();
                return Err(format!("-{name} {}: expected {count} value(s), as in WSClean{}, but {value} is an option", got.join(" "), example(name)));
            }
            values.push(value);
        }
        if command == "dirty" && PRIMARY_BEAM_OPTIONS.contains(&name) {
            return Err(format!("-{name} (WSClean's option): r2d2 dirty writes the dirty image and the PSF only; r2d2 image --apply-primary-beam writes NAME-pb.fits, NAME-image-pb.fits and NAME-model-pb.fits"));
        }
        if command == "dirty" && CLEAN_OPTIONS.contains(&name) {
            // WSClean's dirty image is `-niter 0`: what r2d2 dirty makes.
            if name == "niter" && values[0].parse::<u64>() == Ok(0) {
                continue;
            }
            return Err(format!("-{name} (WSClean's option) controls CLEAN; r2d2 dirty makes the dirty image only (r2d2 image --step clean -{name} ... cleans)"));
        }
        match spelling {
            Spelling::Counterpart(advice) => return Err(format!("-{name} (WSClean's option) has no counterpart in r2d2 {command}: {advice}")),
            Spelling::Same => out.extend(translate(name, &values, &mut rest)?),
        }
    }
    Ok(out)
}

/// Words of only this engine's one-letter flags (`-v`, `-vv`, `-q`, `-h`).
fn is_short_flags(word: &str) -> bool {
    !word.is_empty() && word.chars().all(|c| matches!(c, 'v' | 'q' | 'h'))
}

/// A number (a negative value such as `-0.5` is a value, not an option).
fn is_number(word: &str) -> bool {
    word.parse::<f64>().is_ok()
}

/// A number with an angle's unit (`-30deg`): a value, not an option.
fn is_angle(word: &str) -> bool {
    ["deg", "rad", "asec", "amin"].iter().any(|u| word.strip_suffix(u).is_some_and(is_number))
}

/// How WSClean writes `-name` with its values, where the values are not plain.
fn example(name: &str) -> &'static str {
    match name {
        "size" => " (-size 512 512, width and height; images here are square)",
        _ => "",
    }
}

/// This engine's options for WSClean's `-name values...`.
fn translate(name: &str, values: &[String], rest: &mut std::iter::Peekable<std::vec::IntoIter<String>>) -> Result<Vec<String>, String> {
    // A negative value joined to its option, or clap would read it as one.
    let pair = |option: &str, value: &str| match value.starts_with('-') {
        true => vec![format!("{option}={value}")],
        false => vec![option.to_string(), value.to_string()],
    };
    Ok(match name {
        "size" => {
            if values[0] != values[1] {
                return Err(format!("-size {} {}: images here are square: give one size (--size {})", values[0], values[1], values[0]));
            }
            pair("--size", &values[0])
        }
        "scale" => pair("--pixel-arcsec", &arcsec("scale", &values[0], 3600.0)?.to_string()),
        // WSClean's bare number is arcsec here.
        "taper-gaussian" => pair("--taper-gaussian", &arcsec("taper-gaussian", &values[0], 1.0)?.to_string()),
        // The restoring beam: widths in arcsec by default, the position angle in degrees; the
        // defaults (an elliptical, fitted beam) need no option here.
        "beam-size" => pair("--beam-size", &arcsec("beam-size", &values[0], 1.0)?.to_string()),
        // A negative angle stays a word of its own: clap takes it as one of the three values.
        "beam-shape" => vec![
            "--beam-shape".to_string(),
            arcsec("beam-shape", &values[0], 1.0)?.to_string(),
            arcsec("beam-shape", &values[1], 1.0)?.to_string(),
            degrees("beam-shape", &values[2])?.to_string(),
        ],
        "circular-beam" | "no-fit-beam" | "theoretic-beam" | "join-channels" => vec![format!("--{name}")],
        "channels-out" => pair("--channels-out", &values[0]),
        "channel-range" => vec!["--channels".into(), values[0].clone(), values[1].clone()],
        "elliptical-beam" | "fit-beam" => vec![],
        "minuv-l" | "maxuv-l" | "taper-tukey" | "primary-beam-limit" => pair(&format!("--{name}"), &values[0]),
        "apply-primary-beam" => vec!["--apply-primary-beam".to_string()],
        "weight" => match values[0].to_ascii_lowercase().as_str() {
            "briggs" => {
                let robust = rest.next().ok_or("-weight briggs: expected the robustness, as in WSClean (-weight briggs 0)")?;
                robust.parse::<f64>().map_err(|_| format!("-weight briggs {robust}: expected a number"))?;
                vec!["--weighting".into(), "briggs".into(), format!("--robust={robust}")]
            }
            scheme @ ("natural" | "uniform") => pair("--weighting", scheme),
            other => return Err(format!("-weight {other}: expected briggs R, natural or uniform")),
        },
        "data-column" => pair("--data-column", &values[0]),
        "pol" => match values[0].to_ascii_lowercase().as_str() {
            "i" => pair("--pol", "I"),
            _ => return Err(format!("-pol {}: only Stokes I is imaged here (from I, XX and YY, or RR and LL); -pol I, or leave it out", values[0])),
        },
        "name" => pair("--name", &values[0]),
        "j" => pair("--threads", &values[0]),
        // CLEAN's controls: the same meanings, with --step clean (the engine refuses those a
        // network series does not take, saying so).
        name if CLEAN_OPTIONS.contains(&name) => pair(&format!("--{name}"), &values[0]),
        _ => unreachable!("every Same option is translated"),
    })
}

/// WSClean's angle for `-option` (`1.2asec`, `0.5amin`, `0.01deg`, `10mas`; a bare number is
/// `bare` arcseconds: degrees for -scale, arcseconds for -taper-gaussian, as in WSClean) in
/// arcseconds.
fn arcsec(option: &str, text: &str, bare: f64) -> Result<f64, String> {
    let units = [("masec", 1e-3), ("mas", 1e-3), ("asec", 1.0), ("arcsec", 1.0), ("amin", 60.0), ("arcmin", 60.0), ("deg", 3600.0)];
    let (number, scale) = units.iter().find_map(|(u, s)| text.strip_suffix(u).map(|n| (n, *s))).unwrap_or((text, bare));
    let value: f64 = number.trim().parse().map_err(|_| format!("-{option} {text}: expected an angle such as 1.2asec, 0.5amin or 0.01deg"))?;
    if !(value > 0.0 && value.is_finite()) {
        return Err(format!("-{option} {text}: expected a positive angle"));
    }
    Ok(value * scale)
}

/// WSClean's position angle (`45deg`, `0.5rad`; a bare number is degrees) in degrees.
fn degrees(option: &str, text: &str) -> Result<f64, String> {
    let (number, scale) = [("deg", 1.0), ("rad", 180.0 / std::f64::consts::PI)].iter().find_map(|(u, s)| text.strip_suffix(u).map(|n| (n, *s))).unwrap_or((text, 1.0));
    let value: f64 = number.trim().parse().map_err(|_| format!("-{option} ... {text}: expected an angle such as 45deg or 0.5rad"))?;
    if !value.is_finite() {
        return Err(format!("-{option} ... {text}: expected a finite angle"));
    }
    Ok(value * scale)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn words(text: &str) -> Vec<String> {
        text.split_whitespace().map(str::to_string).collect()
    }

    #[test]
    fn wsclean_spellings_become_this_engines() {
        let got = rewrite(words("r2d2 image -size 512 512 -scale 1.5asec -weight briggs -0.5 -data-column CORRECTED_DATA -name out -j 2 obs.ms")).unwrap();
        assert_eq!(got, words("r2d2 image --size 512 --pixel-arcsec 1.5 --weighting briggs --robust=-0.5 --data-column CORRECTED_DATA --name out --threads 2 obs.ms"));
        assert_eq!(rewrite(words("r2d2 dirty obs.ms --size 256 256 -weight natural")).unwrap(), words("r2d2 dirty obs.ms --size 256 --weighting natural"));
        assert_eq!(rewrite(words("r2d2 image obs.ms -scale 0.01deg")).unwrap()[4], "36");
        // uv cuts and tapers: lengths in wavelengths, the taper's FWHM in arcsec by default.
        assert_eq!(
            rewrite(words("r2d2 dirty obs.ms -minuv-l 100 -maxuv-l 2e5 -taper-tukey 5000 -taper-gaussian 2")).unwrap(),
            words("r2d2 dirty obs.ms --minuv-l 100 --maxuv-l 2e5 --taper-tukey 5000 --taper-gaussian 2")
        );
        assert_eq!(rewrite(words("r2d2 image obs.ms -taper-gaussian 0.5amin")).unwrap()[4], "30");
        assert_eq!(rewrite(words("r2d2 image obs.ms -minuv-l -5")).unwrap(), words("r2d2 image obs.ms --minuv-l=-5"));
        // The restoring beam: widths in arcsec by default, the angle in degrees.
        assert_eq!(
            rewrite(words("r2d2 image obs.ms -beam-shape 1amin 20 -30deg -fit-beam -elliptical-beam")).unwrap(),
            words("r2d2 image obs.ms --beam-shape 60 20 -30")
        );
        assert_eq!(rewrite(words("r2d2 dirty obs.ms -beam-size 0.5amin -no-fit-beam")).unwrap(), words("r2d2 dirty obs.ms --beam-size 30 --no-fit-beam"));
        assert_eq!(rewrite(words("r2d2 dirty obs.ms -pol i")).unwrap(), words("r2d2 dirty obs.ms --pol I"));
        assert_eq!(rewrite(words("r2d2 image obs.ms -channels-out 4 -join-channels -channel-range 2 10")).unwrap(), words("r2d2 image obs.ms --channels-out 4 --join-channels --channels 2 10"));
        assert_eq!(rewrite(words("r2d2 image obs.ms -circular-beam -theoretic-beam")).unwrap(), words("r2d2 image obs.ms --circular-beam --theoretic-beam"));
        // The primary beam: a switch and its cut.
        assert_eq!(
            rewrite(words("r2d2 image -apply-primary-beam obs.ms -primary-beam-limit 0.2")).unwrap(),
            words("r2d2 image --apply-primary-beam obs.ms --primary-beam-limit 0.2")
        );
        // CLEAN's controls, WSClean's meanings (the engine refuses them with a network series).
        assert_eq!(
            rewrite(words("r2d2 image obs.ms --step clean -niter 10000 -auto-threshold 3 -mgain 0.8 -gain 0.1 -threshold 0.001")).unwrap(),
            words("r2d2 image obs.ms --step clean --niter 10000 --auto-threshold 3 --mgain 0.8 --gain 0.1 --threshold 0.001")
        );
        // Masks: a file, and the auto-mask level in noise sigmas.
        assert_eq!(
            rewrite(words("r2d2 image obs.ms --step clean -fits-mask m.fits -auto-mask 5 -auto-threshold 1")).unwrap(),
            words("r2d2 image obs.ms --step clean --fits-mask m.fits --auto-mask 5 --auto-threshold 1")
        );
        // A value joined by `=`, a negative one kept as a value; this engine's one-letter flags
        // and whatever follows `--` pass as they are.
        assert_eq!(rewrite(words("r2d2 image obs.ms --step clean -threshold=-1")).unwrap(), words("r2d2 image obs.ms --step clean --threshold=-1"));
        assert_eq!(rewrite(words("r2d2 image obs.ms -mgain=0.8 -vv -q")).unwrap(), words("r2d2 image obs.ms --mgain 0.8 -vv -q"));
        assert_eq!(rewrite(words("r2d2 image --size 64 -- -odd-name.ms")).unwrap(), words("r2d2 image --size 64 -- -odd-name.ms"));
        // WSClean's dirty image, `-niter 0`, is what r2d2 dirty makes; r2d2 image takes it as
        // CLEAN's (zero components with --step clean; refused with a network series).
        assert_eq!(rewrite(words("r2d2 dirty obs.ms -niter 0 -size 64 64")).unwrap(), words("r2d2 dirty obs.ms --size 64"));
        assert_eq!(rewrite(words("r2d2 dirty obs.ms -niter=0")).unwrap(), words("r2d2 dirty obs.ms"));
        assert_eq!(rewrite(words("r2d2 image obs.ms --step clean -niter 0")).unwrap(), words("r2d2 image obs.ms --step clean --niter 0"));
        // Other commands, and this engine's own spellings, pass untouched.
        assert_eq!(rewrite(words("r2d2 simulate -size 4 4")).unwrap(), words("r2d2 simulate -size 4 4"));
        assert_eq!(rewrite(words("r2d2 -q image obs.ms --size 64 -v")).unwrap(), words("r2d2 -q image obs.ms --size 64 -v"));
    }

    #[test]
    fn wsclean_options_without_counterpart_name_what_to_use() {
        for (line, words_expected) in [
            ("r2d2 dirty obs.ms -niter 10000", &["-niter", "dirty image only", "--step clean"][..]),
            ("r2d2 dirty obs.ms -niter 0 -mgain 0.8", &["-mgain", "dirty image only"][..]),
            ("r2d2 dirty obs.ms -apply-primary-beam", &["-apply-primary-beam", "dirty image and the PSF only", "r2d2 image --apply-primary-beam"][..]),
            ("r2d2 image obs.ms -apply-primary-beam=1", &["-apply-primary-beam takes no value"][..]),
            ("r2d2 dirty obs.ms -fits-mask m.fits", &["-fits-mask", "dirty image only"][..]),
            ("r2d2 image obs.ms -multiscale", &["-multiscale"][..]),
            ("r2d2 image -size 512 256 obs.ms", &["square"][..]),
            ("r2d2 image --size 512 256 obs.ms", &["square"][..]),
            ("r2d2 image -weight briggs", &["robustness"][..]),
            ("r2d2 image -scale 1.2parsec obs.ms", &["1.2parsec", "asec"][..]),
            // WSClean's -size with one number: the next option is not its height.
            ("r2d2 image obs.ms -size 64 --name x", &["-size 64 --name", "expected 2 value(s)", "--name is an option", "-size 512 512"][..]),
            // Options WSClean has and this engine lacks: named whole, not as clap's `-c`.
            ("r2d2 image obs.ms -intervals-out 4", &["-intervals-out: not supported by r2d2 image", "-size, -scale"][..]),
            ("r2d2 dirty obs.ms -taper-edge 4", &["-taper-edge: not supported by r2d2 dirty", "-taper-gaussian"][..]),
            ("r2d2 dirty obs.ms -taper-gaussian -2", &["-taper-gaussian -2", "positive angle"][..]),
            ("r2d2 image obs.ms -multiscale=1", &["-multiscale=1: -multiscale takes no value"][..]),
            ("r2d2 image obs.ms -beam-shape 10 5 north", &["north", "45deg"][..]),
            ("r2d2 image obs.ms -pol IQUV", &["-pol IQUV", "only Stokes I"][..]),
            ("r2d2 image obs.ms -beam-fitting-size 4", &["-beam-fitting-size", "main lobe"][..]),
        ] {
            let e = rewrite(words(line)).unwrap_err();
            for w in words_expected {
                assert!(e.contains(w), "{line}: '{w}' missing from: {e}");
            }
        }
    }
}
