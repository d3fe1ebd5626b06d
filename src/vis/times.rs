//! When the samples were taken, as far as a series' domain goes ([`ObservedTimes`]): how long
//! the observation tracked its source and how long each integration was. Gathered as samples
//! stream in, in memory that does not grow with the samples.
//!
//! A series is trained on tracks of so many hours, each sampled every so many seconds
//! (`track_hours`, `integration_s` in its manifest). Training observes the configurations of a
//! sample one after the other and counts its track as their sum (A 5..10 h + C 1..3 h: 6..13 h).
//! Real data of several configurations were taken days or months apart (`r2d2 simulate` dates
//! them a day apart), so the span from the
//! first to the last sample says nothing; what matches training's count is the time spent
//! tracking: the samples' times fall into tracks (a gap of more than [`TRACK_GAP_S`] starts a
//! new one), and the track length is the sum of their lengths, each from its first to its last
//! integration, both whole. Gaps within a track (calibrator scans) stay in it, as the hour
//! angle the source was tracked over spans them.

use std::collections::BTreeMap;

/// Longest gap between successive integrations within one track, seconds. Calibrator scans
/// and slews leave minutes; other sessions (another configuration, another day) leave hours.
pub const TRACK_GAP_S: f64 = 3600.0;

/// Most tracks gathered: beyond, the times are too scattered to be tracks (corrupt values) and
/// the track length is unknown rather than a sum over as many spans as samples.
const MAX_TRACKS: usize = 10_000;

/// Most distinct integration times counted: beyond, new ones are not counted (the most common
/// one is found long before in any real observation; counts stay bounded for any data).
const MAX_DISTINCT_INTEGRATIONS: usize = 64;

/// Integration times are counted to the millisecond: time stamps carry rounding far below it.
const COUNTS_PER_SECOND: f64 = 1e3;

/// The tracks of the samples seen so far and their integration time.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ObservedTimes {
    /// `[first, last]` sample time (integration centres, seconds) of each track, sorted and
    /// more than [`TRACK_GAP_S`] apart.
    tracks: Vec<[f64; 2]>,
    /// The track the last time fell into: data come in time order, so the next nearly always
    /// does too.
    recent: usize,
    /// Integration times given with the samples (a MeasurementSet's `INTERVAL`), counted by
    /// milliseconds.
    given: BTreeMap<i64, u64>,
    /// Positive steps between successive sample times, counted by milliseconds: the
    /// integration where none is given (the samples of one integration share its time, the
    /// next integration's come one integration later, whether the table is ordered by time or
    /// by baseline).
    steps: BTreeMap<i64, u64>,
    last: Option<f64>,
    /// More than [`MAX_TRACKS`] tracks: the times are not an observation's.
    scattered: bool,
}

impl ObservedTimes {
    /// Whether no sample time was seen (the data carry none).
    pub fn is_empty(&self) -> bool {
        self.tracks.is_empty() && !self.scattered
    }

    /// A sample taken at `time` seconds (its integration's centre); a non-finite time is not
    /// one.
    pub fn add_time(&mut self, time: f64) {
        if !time.is_finite() || self.scattered {
            return;
        }
        if let Some(last) = self.last {
            if time > last {
                count(&mut self.steps, time - last);
            }
        }
        self.last = Some(time);
        self.add_to_tracks([time, time]);
    }

    /// A sample's integration time, seconds, where the data give it; a value that is not a
    /// positive finite number is not one.
    pub fn add_integration(&mut self, seconds: f64) {
        if seconds.is_finite() && seconds > 0.0 {
            count(&mut self.given, seconds);
        }
    }

    /// Adds the times of other samples of the same observation (another batch, another part).
    pub fn merge(&mut self, other: &ObservedTimes) {
        for span in &other.tracks {
            self.add_to_tracks(*span);
        }
        self.scattered |= other.scattered;
        for (counts, theirs) in [(&mut self.given, &other.given), (&mut self.steps, &other.steps)] {
            for (&key, &n) in theirs {
                if counts.len() < MAX_DISTINCT_INTEGRATIONS || counts.contains_key(&key) {
                    *counts.entry(key).or_default() += n;
                }
            }
        }
    }

    /// These times with their integration counts but no track: for a part of the samples whose
    /// own times are then added.
    pub fn without_tracks(&self) -> ObservedTimes {
        ObservedTimes { given: self.given.clone(), steps: self.steps.clone(), ..ObservedTimes::default() }
    }

    /// The integration time, seconds: the most common one given with the samples, else the
    /// most common step between successive times (the shorter of equally common ones). `None`
    /// where neither was seen.
    pub fn integration_s(&self) -> Option<f64> {
        let counts = if self.given.is_empty() { &self.steps } else { &self.given };
        let (&key, _) = counts.iter().max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0)))?;
        Some(key as f64 / COUNTS_PER_SECOND)
    }

    /// The hours the source was tracked, summed over the tracks (module doc): each from its
    /// first to its last integration, both whole. `None` where the data carry no times, they
    /// are scattered beyond any observation's, or they are one time stamp of unknown
    /// integration (a constant column says nothing of the observation).
    pub fn track_hours(&self) -> Option<f64> {
        if self.tracks.is_empty() || self.scattered {
            return None;
        }
        let integration = self.integration_s();
        if integration.is_none() && self.tracks.iter().all(|[first, last]| first == last) {
            return None;
        }
        let seconds: f64 = self.tracks.iter().map(|[first, last]| last - first + integration.unwrap_or(0.0)).sum();
        let hours = seconds / 3600.0;
        hours.is_finite().then_some(hours)
    }

    /// The number of tracks the times fall into (0: unknown).
    pub fn tracks(&self) -> usize {
        if self.scattered {
            0
        } else {
            self.tracks.len()
        }
    }

    fn add_to_tracks(&mut self, [first, last]: [f64; 2]) {
        let near = |track: &[f64; 2]| first <= track[1] + TRACK_GAP_S && last >= track[0] - TRACK_GAP_S;
        let at = match self.tracks.get(self.recent) {
            Some(track) if near(track) => self.recent,
            _ => {
                let at = self.tracks.partition_point(|track| track[1] + TRACK_GAP_S < first);
                if !self.tracks.get(at).is_some_and(near) {
                    if self.tracks.len() >= MAX_TRACKS {
                        self.scattered = true;
                        self.tracks.clear();
                        return;
                    }
                    self.tracks.insert(at, [first, last]);
                    self.recent = at;
                    return;
                }
                at
            }
        };
        let track = &mut self.tracks[at];
        track[0] = track[0].min(first);
        track[1] = track[1].max(last);
        // Grown, it may now reach its neighbours.
        let mut at = at;
        while at > 0 && self.tracks[at - 1][1] + TRACK_GAP_S >= self.tracks[at][0] {
            let [first, last] = self.tracks.remove(at);
            at -= 1;
            self.tracks[at] = [self.tracks[at][0].min(first), self.tracks[at][1].max(last)];
        }
        while at + 1 < self.tracks.len() && self.tracks[at][1] + TRACK_GAP_S >= self.tracks[at + 1][0] {
            let [first, last] = self.tracks.remove(at + 1);
            self.tracks[at] = [self.tracks[at][0].min(first), self.tracks[at][1].max(last)];
        }
        self.recent = at;
    }
}

/// Counts `seconds` at the millisecond (a step shorter than one is rounding, not a step).
fn count(counts: &mut BTreeMap<i64, u64>, seconds: f64) {
    // A step between times as far apart as f64 allows is no integration.
    if !seconds.is_finite() {
        return;
    }
    let key = (seconds * COUNTS_PER_SECOND).round() as i64;
    if key > 0 && (counts.len() < MAX_DISTINCT_INTEGRATIONS || counts.contains_key(&key)) {
        *counts.entry(key).or_default() += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Times of `n` integrations of `step` seconds from `start`, each for `baselines` samples.
    fn track(times: &mut ObservedTimes, start: f64, n: usize, step: f64, baselines: usize) {
        for k in 0..n {
            for _ in 0..baselines {
                times.add_time(start + (k as f64 + 0.5) * step);
            }
        }
    }

    #[test]
    fn one_track_lasts_from_its_first_to_its_last_integration() {
        let mut times = ObservedTimes::default();
        track(&mut times, 4.9e9, 48, 300.0, 3);
        assert_eq!(times.integration_s(), Some(300.0));
        assert!((times.track_hours().unwrap() - 4.0).abs() < 1e-9, "{:?}", times.track_hours());
    }

    #[test]
    fn tracks_days_apart_add_up_and_back_to_back_ones_are_one() {
        // A configuration of 6 h, another of 2 h thirty days later, in either order.
        let (a, c) = (4.9e9, 4.9e9 + 30.0 * 86_400.0);
        for order in [[a, c], [c, a]] {
            let mut times = ObservedTimes::default();
            track(&mut times, order[0], if order[0] == a { 72 } else { 24 }, 300.0, 2);
            track(&mut times, order[1], if order[1] == a { 72 } else { 24 }, 300.0, 2);
            assert_eq!(times.tracks(), 2);
            assert!((times.track_hours().unwrap() - 8.0).abs() < 1e-9);
        }
        // As training's coverage holds them: one after the other.
        let mut times = ObservedTimes::default();
        track(&mut times, 0.0, 72, 300.0, 2);
        track(&mut times, 6.0 * 3600.0, 24, 300.0, 2);
        assert_eq!(times.tracks(), 1);
        assert!((times.track_hours().unwrap() - 8.0).abs() < 1e-9);
    }

    #[test]
    fn a_given_integration_comes_before_the_steps_and_parts_merge() {
        let (mut first, mut second) = (ObservedTimes::default(), ObservedTimes::default());
        // Ordered by baseline: each baseline's times run through the track again.
        for _ in 0..3 {
            track(&mut first, 0.0, 30, 8.0, 1);
        }
        assert_eq!(first.integration_s(), Some(8.0));
        track(&mut second, 7200.0, 10, 8.0, 1);
        for _ in 0..10 {
            second.add_integration(8.0);
        }
        second.add_integration(2.0);
        first.merge(&second);
        assert_eq!(first.integration_s(), Some(8.0));
        assert_eq!(first.tracks(), 2);
        assert!((first.track_hours().unwrap() - 40.0 * 8.0 / 3600.0).abs() < 1e-9);
    }

    #[test]
    fn data_without_times_or_with_bad_ones_know_no_track() {
        let mut times = ObservedTimes::default();
        assert_eq!((times.track_hours(), times.integration_s()), (None, None));
        for t in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            times.add_time(t);
            times.add_integration(t);
        }
        times.add_integration(-3.0);
        times.add_integration(0.0);
        assert!(times.is_empty());
        // A constant column (times all 0) says nothing.
        for _ in 0..5 {
            times.add_time(0.0);
        }
        assert_eq!((times.track_hours(), times.integration_s()), (None, None));
        // Times spread over ages: scattered, not tracks; bounded memory, no panic.
        let mut scattered = ObservedTimes::default();
        for k in 0..(MAX_TRACKS + 5) {
            scattered.add_time(k as f64 * 1e7);
        }
        scattered.add_time(f64::MAX);
        scattered.add_time(-f64::MAX);
        assert_eq!((scattered.track_hours(), scattered.tracks()), (None, 0));
        let mut extreme = ObservedTimes::default();
        extreme.add_time(-f64::MAX);
        extreme.add_time(f64::MAX);
        assert_eq!(extreme.track_hours(), None, "two times as far apart as f64 allows");
    }
}
