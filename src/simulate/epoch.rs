//! When a simulated observation took place. `r2d2 simulate` observes configuration `k` of an
//! observation on day `k` after [`REFERENCE_MJD`] (2025-06-01 UTC), its track centred on the
//! transit of the phase centre nearest that day's noon: its times are then those of a real
//! observation (MJD seconds, UTC, as a MeasurementSet's TIME), with the hour angles the uv
//! tracks were computed for, and configurations a day apart are tracks of their own for the
//! domain check (`vis::times`).

use super::telescope::SIDEREAL_PER_SOLAR;
use std::f64::consts::TAU;

/// 2025-06-01 00:00 UTC as a Modified Julian Date: the day the first configuration is observed.
pub const REFERENCE_MJD: f64 = 60_827.0;

/// Seconds per day: MS times are MJD days times this.
pub const SECONDS_PER_DAY: f64 = 86_400.0;

/// Greenwich mean sidereal time at `mjd` (UTC), radians in [0, 2 pi): the IAU 1982 formula
/// (Aoki et al. 1982) in UT1, taking UT1 as UTC. |UT1 - UTC| stays below 0.9 s, a fraction of
/// an integration, and no table of it is compiled in.
pub fn gmst_rad(mjd: f64) -> f64 {
    // Julian centuries of UT1 from J2000.0 (JD 2451545.0 = MJD 51544.5).
    let t = (mjd - 51_544.5) / 36_525.0;
    let seconds = 67_310.548_41 + (876_600.0 * 3600.0 + 8_640_184.812_866) * t + 0.093_104 * t * t - 6.2e-6 * t * t * t;
    (seconds.rem_euclid(SECONDS_PER_DAY) / SECONDS_PER_DAY) * TAU
}

/// The instant (MJD, UTC) nearest `near_mjd` at which the local mean sidereal time at east
/// longitude `longitude_rad` equals `ra_rad`: the source's transit there.
pub fn transit_mjd(ra_rad: f64, longitude_rad: f64, near_mjd: f64) -> f64 {
    let mut mjd = near_mjd;
    // The first step lands within rounding of the transit (the sidereal rate is constant to
    // 1e-10), the others remove that.
    for _ in 0..3 {
        let hour_angle = (gmst_rad(mjd) + longitude_rad - ra_rad + TAU / 2.0).rem_euclid(TAU) - TAU / 2.0;
        mjd -= hour_angle / (TAU * SIDEREAL_PER_SOLAR);
    }
    mjd
}

/// The transit (MJD, UTC) a track of day `day` after [`REFERENCE_MJD`] is centred on: the one
/// nearest that day's noon, so that consecutive days' tracks are a sidereal day apart.
pub fn transit_on_day(ra_rad: f64, longitude_rad: f64, day: usize) -> f64 {
    transit_mjd(ra_rad, longitude_rad, REFERENCE_MJD + day as f64 + 0.5)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hms(h: f64, m: f64, s: f64) -> f64 {
        (h + m / 60.0 + s / 3600.0) / 24.0 * TAU
    }

    /// Meeus, Astronomical Algorithms, examples 12.a and 12.b: 1987 April 10 at 0h UT and at
    /// 19:21:00 UT.
    #[test]
    fn gmst_is_the_textbook_value() {
        let second = TAU / SECONDS_PER_DAY;
        for (mjd, expected) in [(46_895.0, hms(13.0, 10.0, 46.3668)), (46_895.0 + 19.35 / 24.0, hms(8.0, 34.0, 57.0896))] {
            let error = (gmst_rad(mjd) - expected).abs() / second;
            assert!(error < 1e-3, "{mjd}: {error} s");
        }
    }

    #[test]
    fn the_transit_has_the_source_on_the_meridian_near_the_day_s_noon() {
        let second = TAU / SECONDS_PER_DAY;
        for (ra_deg, lon_deg) in [(0.0f64, -107.6f64), (180.0, 21.4), (359.9, 0.0), (45.0, 179.9)] {
            let (ra, lon) = (ra_deg.to_radians(), lon_deg.to_radians());
            for day in [0, 1, 200] {
                let t = transit_on_day(ra, lon, day);
                let lst = (gmst_rad(t) + lon).rem_euclid(TAU);
                let off = ((lst - ra + TAU / 2.0).rem_euclid(TAU) - TAU / 2.0).abs() / second;
                assert!(off < 1e-3, "ra {ra_deg} lon {lon_deg} day {day}: {off} s");
                let noon = REFERENCE_MJD + day as f64 + 0.5;
                assert!((t - noon).abs() <= 0.5 / SIDEREAL_PER_SOLAR + 1e-9, "{t} vs {noon}");
            }
            // A sidereal day apart (two where the transit nearest noon wraps round the day).
            let step = transit_on_day(ra, lon, 1) - transit_on_day(ra, lon, 0);
            assert!((step - 1.0 / SIDEREAL_PER_SOLAR).abs() < 1e-8 || (step - 2.0 / SIDEREAL_PER_SOLAR).abs() < 1e-8, "{step}");
        }
    }
}
