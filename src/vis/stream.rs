//! Visibilities read in passes, a chunk at a time ([`VisSource`]): held in memory, or read
//! again from their file at every pass, so that imaging a table needs memory for one chunk,
//! not for the table. What a pass over the whole table tells before imaging starts (the
//! longest baseline, the band, |w|) is a [`VisSummary`].

use super::convert::{record_batch_to_visibilities, IngestStats};
use super::data::{ObservationMeta, VisChunk, Visibilities, VisSummary};
use super::parted::PartedObservation;
use super::reader::TableReader;
use super::spill::Spill;
use crate::{Error, Result};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Opens the table again for another pass (its reader, positioned at the first row).
pub type Reopen = dyn Fn() -> Result<Box<dyn TableReader>> + Send + Sync;

/// A job's visibilities: held in memory, read again from their file at every pass, or kept
/// in parts gridded where they live (each pass a sum over the parts, made by the parts' own
/// [`PartPasses`](super::PartPasses)).
#[derive(Clone)]
pub enum VisSource {
    Held(Arc<Visibilities>),
    Streamed(Arc<StreamedTable>),
    Parts(Arc<PartedObservation>),
}

/// Decoded batches a first reading holds between decoding and keeping them.
const BATCHES_IN_FLIGHT: usize = 2;

/// What a first reading keeps of a table: its counts, its summary, its digest and its
/// decoded copy.
struct Kept {
    stats: IngestStats,
    summary: VisSummary,
    digest: SampleDigest,
    spill: Option<std::result::Result<Spill, super::spill::NoSpill>>,
}

/// A checksum of decoded samples in their order (every column, to the bit): two readings of
/// one table agree on it, while a table replaced by another with as many samples (its
/// baselines, weights or values changed) does not, though its counts are the same.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct SampleDigest([u64; 4]);

impl SampleDigest {
    /// Folds `vis`'s samples in: four independent lanes (baselines, values, weights,
    /// frequencies), each a multiply-rotate hash of the values' bits, cheap beside decoding.
    fn add(&mut self, vis: &Visibilities) {
        const K: u64 = 0x9e37_79b9_7f4a_7c15;
        let fold = |lane: &mut u64, bits: u64| *lane = (lane.rotate_left(23) ^ bits).wrapping_mul(K);
        let [baselines, values, weights, frequencies] = &mut self.0;
        for k in 0..vis.len() {
            fold(baselines, vis.u[k].to_bits());
            fold(baselines, vis.v[k].to_bits());
            fold(baselines, vis.w[k].to_bits());
            fold(values, u64::from(vis.vis[k].re.to_bits()) << 32 | u64::from(vis.vis[k].im.to_bits()));
            let imaging_weight = vis.imaging_weight.get(k).map_or(u64::MAX, |x| u64::from(x.to_bits()));
            fold(weights, u64::from(vis.weight[k].to_bits()) << 32 ^ imaging_weight);
        }
        for f in &vis.frequency {
            fold(frequencies, f.to_bits());
        }
    }
}

/// What the first reading of one part of an observation found (its samples and their
/// digest), for each later pass over the part to be checked against: such a pass opens the
/// part again where it lives (a Dask worker), so the check travels with the pass, as text.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PartCheck {
    samples: u64,
    digest: SampleDigest,
}

impl PartCheck {
    /// `SAMPLES:DIGEST`, the digest as 64 hex digits.
    pub fn to_text(&self) -> String {
        let [a, b, c, d] = self.digest.0;
        format!("{}:{a:016x}{b:016x}{c:016x}{d:016x}", self.samples)
    }

    pub fn from_text(text: &str) -> Result<PartCheck> {
        let parsed = text.split_once(':').and_then(|(samples, digest)| {
            let lane = |k: usize| digest.get(16 * k..16 * (k + 1)).and_then(|hex| u64::from_str_radix(hex, 16).ok());
            let digest = SampleDigest([lane(0)?, lane(1)?, lane(2)?, lane(3)?]);
            (text.len() == text.find(':')? + 65).then_some(())?;
            Some(PartCheck { samples: samples.parse().ok()?, digest })
        });
        parsed.ok_or_else(|| Error::parameter("check", format!("expected what a part's first reading found, as SAMPLES:DIGEST (64 hex digits; the `check` of its summary), got {text:.100}")))
    }
}

/// The error of a pass over the part `path` that found `now` where its first reading found
/// `first`.
pub(crate) fn part_changed(path: &Path, first: &PartCheck, now: &PartCheck) -> Error {
    let found = if now.samples == first.samples {
        format!("as many samples as its first reading ({}) but other values (baselines, visibilities, weights or frequencies)", first.samples)
    } else if now.samples > first.samples {
        format!("more samples than the {} its first reading found", first.samples)
    } else {
        format!("{} samples where its first reading found {}", now.samples, first.samples)
    };
    Error::input(path, format!("this part of the observation changed between passes: a later pass found {found} (was it replaced or written to meanwhile?); nothing was written"))
}

/// A table read again from its file at every pass. Each pass must find the samples the first
/// found (their counts and their digest): a file changed or replaced under a running job is
/// an error, not an image of two tables.
pub struct StreamedTable {
    path: PathBuf,
    reopen: Box<Reopen>,
    meta: ObservationMeta,
    stats: IngestStats,
    /// The first reading's samples, for later passes to be checked against.
    digest: SampleDigest,
    /// Whether `stats` are the first reading's, for later passes to be checked against
    /// (false for a table opened for one pass without reading it first).
    scanned: bool,
    summary: VisSummary,
    reader_summary: Option<String>,
    /// The samples as the first reading decoded them, read back by every later pass in place
    /// of the file (`None`: the file is read again at each pass).
    spill: Option<Spill>,
    /// What a first reading elsewhere found, for a part opened for one pass.
    expected: Option<PartCheck>,
}

impl StreamedTable {
    /// Reads the table once through `reader`, counting its samples and what imaging needs to
    /// know of them. The samples are not kept in memory: where `spill_in` names a directory
    /// fit for it, they are kept decoded in a temporary file there ([`super::spill`]) for
    /// the later passes; otherwise `reopen` gives the table's reader again for each later
    /// pass. `cancelled` is polled at every batch (`None`: it turned true).
    pub fn scan(mut reader: Box<dyn TableReader>, reopen: Box<Reopen>, spill_in: Option<&Path>, cancelled: &dyn Fn() -> bool) -> Result<Option<StreamedTable>> {
        let source = reader.source().display().to_string();
        // Two threads: this one decodes the file's batches, the keeper converts them, sums them
        // up and writes the decoded copy; neither waits on the other's system calls (a
        // MeasurementSet's mapped pages, the copy's writes) but for a batch or two in flight.
        let kept = std::thread::scope(|scope| -> Result<Option<Kept>> {
            let (to_keeper, batches) = std::sync::mpsc::sync_channel::<arrow::array::RecordBatch>(BATCHES_IN_FLIGHT);
            let source = source.as_str();
            let keeper = std::thread::Builder::new().name("r2d2-keeper".into()).spawn_scoped(scope, move || -> Result<Kept> {
                let mut kept = Kept { stats: IngestStats::default(), summary: VisSummary::empty(), digest: SampleDigest::default(), spill: spill_in.map(Spill::create) };
                for batch in batches {
                    let vis = record_batch_to_visibilities(&batch, &mut kept.stats, source)?;
                    kept.summary.add_visibilities(&vis);
                    kept.digest.add(&vis);
                    if let Some(Ok(copy)) = &mut kept.spill {
                        if let Err(why) = copy.append(&vis) {
                            kept.spill = Some(Err(why)); // the incomplete copy is dropped (and its space freed) here
                        }
                    }
                }
                Ok(kept)
            });
            let keeper = keeper.map_err(|e| Error::OutOfMemory(format!("cannot start the thread that keeps {source}'s samples: {e} (is the address space limited? ulimit -v)")))?;
            let mut outcome = Ok(true);
            while let Some(batch) = reader.next_batch() {
                if cancelled() {
                    outcome = Ok(false);
                    break;
                }
                match batch {
                    // A send fails only where the keeper stopped on an error, reported below.
                    Ok(batch) => {
                        if to_keeper.send(batch).is_err() {
                            break;
                        }
                    }
                    Err(e) => {
                        outcome = Err(e);
                        break;
                    }
                }
            }
            drop(to_keeper);
            // A panic of the keeper is a bug, not a fault of the file: it goes on to the stage's
            // containment, as it would have on one thread.
            let kept = keeper.join().unwrap_or_else(|payload| std::panic::resume_unwind(payload));
            // The keeper's error is of an earlier batch than any the reading met after it.
            let kept = kept?;
            Ok(outcome?.then_some(kept))
        })?;
        let Some(Kept { stats, summary, digest, spill }) = kept else { return Ok(None) };
        let spill = match spill {
            Some(Ok(kept)) => {
                log::info!(
                    "{source}: the samples are kept decoded in a temporary file ({}) for the passes after the first",
                    crate::limits::format_bytes(kept.bytes() as f64)
                );
                Some(kept)
            }
            Some(Err(why)) => {
                log::info!("{source}: each pass reads the table again (no temporary copy of its samples: {why})");
                None
            }
            None => None,
        };
        Ok(Some(StreamedTable {
            path: reader.source().to_path_buf(),
            reopen,
            meta: reader.meta().clone(),
            stats,
            digest,
            scanned: true,
            summary,
            reader_summary: reader.summary(),
            spill,
            expected: None,
        }))
    }

    /// A table for passes not checked against a reading of its own (nothing is read now; its
    /// summary is empty): one part of an observation, each pass checked against `expected`,
    /// what the part's first reading found where it was summarised.
    pub fn unscanned(reader: Box<dyn TableReader>, reopen: Box<Reopen>, expected: Option<PartCheck>) -> StreamedTable {
        StreamedTable {
            path: reader.source().to_path_buf(),
            reopen,
            meta: reader.meta().clone(),
            stats: IngestStats::default(),
            digest: SampleDigest::default(),
            scanned: false,
            summary: VisSummary::empty(),
            reader_summary: None,
            spill: None,
            expected,
        }
    }

    pub fn stats(&self) -> &IngestStats {
        &self.stats
    }
    pub fn path(&self) -> &Path {
        &self.path
    }
    pub fn meta(&self) -> &ObservationMeta {
        &self.meta
    }
    /// What each pass after the first reads: the table's decoded temporary copy, or the file.
    pub fn read_by_each_pass(&self) -> String {
        match &self.spill {
            Some(_) => format!("a decoded copy of {}", self.path.display()),
            None => self.path.display().to_string(),
        }
    }

    /// What the reader had to say of the table once read (a MeasurementSet's rows skipped).
    pub fn reader_summary(&self) -> Option<&str> {
        self.reader_summary.as_deref()
    }

    /// Longest projected baseline of the samples kept, wavelengths.
    pub fn max_uv(&self) -> f64 {
        self.summary.max_uv
    }
}

impl VisSource {
    pub fn summary(&self) -> VisSummary {
        match self {
            VisSource::Held(vis) => VisSummary::of(vis),
            VisSource::Streamed(table) => table.summary.clone(),
            VisSource::Parts(parts) => parts.summary.clone(),
        }
    }

    pub fn len(&self) -> usize {
        match self {
            VisSource::Held(vis) => vis.len(),
            VisSource::Streamed(table) => table.summary.samples as usize,
            VisSource::Parts(parts) => parts.summary.samples as usize,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// What the first reading of these samples found, for passes over them elsewhere to be
    /// checked against: `None` for parts (each has its own) or a table not read first.
    pub fn part_check(&self) -> Option<PartCheck> {
        match self {
            VisSource::Held(vis) => {
                let mut digest = SampleDigest::default();
                digest.add(vis);
                Some(PartCheck { samples: vis.len() as u64, digest })
            }
            VisSource::Streamed(table) => table.scanned.then_some(PartCheck { samples: table.stats.kept(), digest: table.digest }),
            VisSource::Parts(_) => None,
        }
    }

    /// Whether each pass reads the samples again (from their file, or where their parts live).
    pub fn is_streamed(&self) -> bool {
        !matches!(self, VisSource::Held(_))
    }

    /// Calls `f` with every sample, in chunks of at most `chunk_rows` (held data) or one
    /// decoded batch (a file), in the table's order.
    pub fn for_each_chunk(&self, chunk_rows: usize, f: &mut dyn FnMut(VisChunk<'_>) -> Result<()>) -> Result<()> {
        match self {
            VisSource::Held(vis) => {
                let n = vis.len();
                let step = chunk_rows.max(1);
                for start in (0..n).step_by(step) {
                    f(vis.chunk(start..(start + step).min(n)))?;
                }
                Ok(())
            }
            VisSource::Streamed(table) => {
                if let Some(spill) = &table.spill {
                    return spill.for_each_chunk(chunk_rows, &table.path, &mut |buffer| f(buffer.chunk(0..buffer.len())));
                }
                let mut reader = (table.reopen)()?;
                let source = reader.source().display().to_string();
                let mut stats = IngestStats::default();
                let mut digest = SampleDigest::default();
                // Batches are gathered into chunks of `chunk_rows`: a consumer's cost per call
                // (sorting, merging grids) is then paid per chunk, not per batch. One buffer for
                // every chunk: fresh pages cost a fault each, chunk after chunk otherwise.
                let mut buffer = Visibilities::default();
                while let Some(batch) = reader.next_batch() {
                    let vis = record_batch_to_visibilities(&batch?, &mut stats, &source)?;
                    let expected_samples = table.expected.map_or(table.stats.kept(), |check| check.samples);
                    let checked = table.scanned || table.expected.is_some();
                    if checked && stats.kept() > expected_samples {
                        break;
                    }
                    if checked {
                        digest.add(&vis);
                    }
                    if buffer.is_empty() && vis.len() >= chunk_rows {
                        f(vis.chunk(0..vis.len()))?;
                        continue;
                    }
                    buffer.push_batch(vis);
                    if buffer.len() >= chunk_rows {
                        f(buffer.chunk(0..buffer.len()))?;
                        buffer.clear();
                    }
                }
                if table.scanned && stats != table.stats {
                    return Err(Error::input(
                        &table.path,
                        format!(
                            "the table changed while it was imaged: its first reading found {}, a later one {} (was it written to meanwhile?); nothing was written",
                            table.stats, stats
                        ),
                    ));
                }
                if table.scanned && digest != table.digest {
                    return Err(Error::input(
                        &table.path,
                        format!(
                            "the table changed while it was imaged: a later reading found as many samples as the first ({stats}) but other values (baselines, visibilities, weights or frequencies; was it replaced or written to meanwhile?); nothing was written"
                        ),
                    ));
                }
                if let Some(first) = &table.expected {
                    let now = PartCheck { samples: stats.kept(), digest };
                    if now != *first {
                        return Err(part_changed(&table.path, first, &now));
                    }
                }
                if !buffer.is_empty() {
                    f(buffer.chunk(0..buffer.len()))?;
                }
                Ok(())
            }
            VisSource::Parts(parts) => Err(not_here(parts)),
        }
    }

    /// The samples in memory, taken out of the source: the held ones (copied only where
    /// another holder shares them), or the file read whole.
    pub fn into_held(self) -> Result<Visibilities> {
        match self {
            VisSource::Held(vis) => Ok(Arc::try_unwrap(vis).unwrap_or_else(|shared| Visibilities::clone(&shared))),
            streamed => streamed.read_all(),
        }
    }

    /// The samples in memory: the held ones, or the file read whole (for a caller that
    /// needs them all at once, such as an operator kept for the residual update).
    pub fn read_all(&self) -> Result<Visibilities> {
        match self {
            VisSource::Held(vis) => Ok(Visibilities::clone(vis)),
            VisSource::Parts(parts) => Err(not_here(parts)),
            VisSource::Streamed(table) => {
                let mut all = Visibilities { times: table.summary.times.clone(), ..Visibilities::with_capacity(table.summary.samples as usize) };
                self.for_each_chunk(1 << 20, &mut |c| {
                    all.u.extend_from_slice(c.u);
                    all.v.extend_from_slice(c.v);
                    all.w.extend_from_slice(c.w);
                    all.vis.extend_from_slice(c.vis);
                    all.weight.extend_from_slice(c.weight);
                    all.frequency.extend_from_slice(c.frequency);
                    all.imaging_weight.extend_from_slice(c.imaging_weight);
                    Ok(())
                })?;
                Ok(all)
            }
        }
    }
}

/// The error of a stage that needs the samples of a parted observation in this process.
fn not_here(parts: &PartedObservation) -> Error {
    Error::parameter(
        "observation",
        format!(
            "job '{}' is kept in {}, which are gridded where they live: this needs its samples in one process (image it with the PSF-convolution residual, and write no model column)",
            parts.id,
            parts.passes.describe()
        ),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use num_complex::Complex32;

    #[test]
    fn held_chunks_cover_every_sample_once_in_order() {
        let n = 10;
        let vis = Visibilities {
            u: (0..n).map(|k| k as f64).collect(),
            v: vec![1.0; n],
            w: vec![0.5; n],
            vis: vec![Complex32::new(1.0, 0.0); n],
            weight: vec![2.0; n],
            frequency: (0..n).map(|k| 1e9 + k as f64).collect(),
            ..Visibilities::default()
        };
        let source = VisSource::Held(Arc::new(vis.clone()));
        let mut seen = Vec::new();
        source
            .for_each_chunk(3, &mut |c| {
                assert!(c.len() <= 3 && c.imaging_weight.is_empty());
                seen.extend_from_slice(c.u);
                Ok(())
            })
            .unwrap();
        assert_eq!(seen, vis.u);
        let s = source.summary();
        assert_eq!((s.samples, s.max_abs_w, s.band()), (10, 0.5, Some((1e9 + 4.5, Some(9.0)))));
        assert_eq!(s.max_uv, 9f64.hypot(1.0));
        assert_eq!(source.read_all().unwrap(), vis);
    }

    /// A table of `rows` samples in memory, as a reader.
    fn table(rows: usize) -> Box<dyn TableReader> {
        table_changed(rows, |_| {})
    }

    /// `table(rows)` with `change` made to its columns.
    fn table_changed(rows: usize, change: fn(&mut super::super::table::VisTable)) -> Box<dyn TableReader> {
        use super::super::table::{to_record_batches, VisTable};
        let mut t = VisTable {
            u_m: (0..rows).map(|k| 10.0 + k as f64).collect(),
            v_m: vec![5.0; rows],
            w_m: vec![1.0; rows],
            frequency: vec![1.4e9; rows],
            vis: vec![num_complex::Complex64::new(1.0, 0.0); rows],
            weight: vec![1.0; rows],
            flag: vec![false; rows],
            time: vec![0.0; rows],
            antenna1: vec![0; rows],
            antenna2: vec![1; rows],
        };
        change(&mut t);
        let meta = super::super::ObservationMeta::new(10.0, 20.0, "VLA");
        let (schema, batches) = to_record_batches(&t, &meta, 4).unwrap();
        let input = super::super::MemoryInput::from_batches("t", schema, batches);
        Box::new(crate::vis::memory::memory_table(input, "t").unwrap())
    }

    /// A table whose first reading finds 10 samples and every later one 9 (a file written
    /// meanwhile), read once and scanned (its copy kept in `spill_in`); and how many times it
    /// was opened.
    fn changing_table(spill_in: Option<&Path>) -> (StreamedTable, Arc<std::sync::atomic::AtomicUsize>) {
        use std::sync::atomic::{AtomicUsize, Ordering};
        let opened = Arc::new(AtomicUsize::new(0));
        let counter = opened.clone();
        let reopen = move || Ok(table(if counter.fetch_add(1, Ordering::SeqCst) == 0 { 10 } else { 9 }));
        let first = reopen().unwrap();
        (StreamedTable::scan(first, Box::new(reopen), spill_in, &|| false).unwrap().unwrap(), opened)
    }

    /// The sizes of the chunks of at least 3 samples a pass gives.
    fn chunk_sizes(source: &VisSource) -> Vec<usize> {
        let mut sizes = Vec::new();
        source
            .for_each_chunk(3, &mut |c| {
                sizes.push(c.len());
                Ok(())
            })
            .unwrap();
        sizes
    }

    /// `table(10)` (batches of 4) whose batch `at` is replaced: by a read error, or by a
    /// batch the conversion refuses (no sample columns).
    struct Faulty {
        inner: Box<dyn TableReader>,
        served: usize,
        at: usize,
        read_error: bool,
    }

    impl TableReader for Faulty {
        fn source(&self) -> &Path {
            self.inner.source()
        }
        fn meta(&self) -> &ObservationMeta {
            self.inner.meta()
        }
        fn schema(&self) -> arrow::datatypes::SchemaRef {
            self.inner.schema()
        }
        fn next_batch(&mut self) -> Option<Result<arrow::array::RecordBatch>> {
            let batch = self.inner.next_batch()?;
            self.served += 1;
            if self.served - 1 != self.at {
                return Some(batch);
            }
            Some(if self.read_error {
                Err(Error::input("t", "the disk failed at batch 2"))
            } else {
                let column: arrow::array::ArrayRef = Arc::new(arrow::array::Float64Array::from(vec![1.0; 4]));
                Ok(arrow::array::RecordBatch::try_from_iter([("unrelated", column)]).unwrap())
            })
        }
    }

    #[test]
    fn the_first_reading_reports_a_failed_batch_and_stops_when_cancelled() {
        let faulty = |read_error| -> Box<dyn TableReader> { Box::new(Faulty { inner: table(10), served: 0, at: 1, read_error }) };
        let dir = tempfile::tempdir().unwrap();
        for spill_in in [None, Some(dir.path())] {
            // A batch that cannot be read, and one the keeping thread cannot convert, are each
            // the scan's error; a cancelled scan returns no table.
            let e = StreamedTable::scan(faulty(true), Box::new(|| Ok(table(10))), spill_in, &|| false).err().unwrap().to_string();
            assert!(e.contains("the disk failed at batch 2"), "{e}");
            let e = StreamedTable::scan(faulty(false), Box::new(|| Ok(table(10))), spill_in, &|| false).err().unwrap().to_string();
            assert!(e.contains("t: missing required column `u`"), "{e}");
            let seen = std::sync::atomic::AtomicUsize::new(0);
            let cancel_after_one = || seen.fetch_add(1, std::sync::atomic::Ordering::SeqCst) >= 1;
            assert!(StreamedTable::scan(table(10), Box::new(|| Ok(table(10))), spill_in, &cancel_after_one).unwrap().is_none());
            // Untouched, every sample is counted once, in order.
            let whole = StreamedTable::scan(table(10), Box::new(|| Ok(table(10))), spill_in, &|| false).unwrap().unwrap();
            assert_eq!((whole.stats().kept(), whole.summary.samples), (10, 10));
            let mut u = Vec::new();
            VisSource::Streamed(Arc::new(whole))
                .for_each_chunk(1, &mut |c| {
                    u.extend_from_slice(c.u);
                    Ok(())
                })
                .unwrap();
            assert_eq!(u.len(), 10);
            assert!(u.windows(2).all(|p| p[0] < p[1]), "{u:?}");
        }
    }

    #[test]
    fn a_table_that_changes_between_passes_is_an_error_naming_it() {
        let (streamed, _) = changing_table(None);
        assert_eq!((streamed.stats().kept(), streamed.summary.samples), (10, 10));
        let source = VisSource::Streamed(Arc::new(streamed));
        let e = source.for_each_chunk(3, &mut |_| Ok(())).unwrap_err().to_string();
        assert!(e.contains("t:") && e.contains("changed while it was imaged"), "{e}");
        // One that stays the same is read whole in chunks of at least 3 (its batches of 4).
        let same = StreamedTable::scan(table(10), Box::new(|| Ok(table(10))), None, &|| false).unwrap().unwrap();
        assert_eq!(chunk_sizes(&VisSource::Streamed(Arc::new(same))), vec![4, 4, 2]);
    }

    /// A table replaced after its first reading by one of as many samples (as with `TMPDIR`
    /// on tmpfs, where nothing is spilled and each pass reads the file) is an error, whichever
    /// column differs: its counts alone are the same.
    #[test]
    fn a_table_replaced_by_one_of_as_many_samples_is_an_error_naming_it() {
        use super::super::table::VisTable;
        use std::sync::atomic::{AtomicUsize, Ordering};
        let changes: [(&str, fn(&mut VisTable)); 5] = [
            ("w x 0.9", |t| t.w_m.iter_mut().for_each(|w| *w *= 0.9)),
            ("u", |t| t.u_m[3] += 1e-9),
            ("weights", |t| t.weight[9] = 2.0),
            ("values", |t| t.vis[0].im = 1e-3),
            ("frequencies", |t| t.frequency[5] = 1.5e9),
        ];
        for (what, change) in changes {
            let opened = Arc::new(AtomicUsize::new(0));
            let reopen = move || Ok(if opened.fetch_add(1, Ordering::SeqCst) == 0 { table(10) } else { table_changed(10, change) });
            let first = reopen().unwrap();
            let streamed = StreamedTable::scan(first, Box::new(reopen), None, &|| false).unwrap().unwrap();
            let e = VisSource::Streamed(Arc::new(streamed)).for_each_chunk(3, &mut |_| Ok(())).unwrap_err().to_string();
            assert!(e.contains("t:") && e.contains("as many samples as the first (10 samples read, 10 kept") && e.contains("other values"), "{what}: {e}");
        }
    }

    /// With a temporary copy, later passes read the samples the first reading decoded, and
    /// never the file again: the same samples pass after pass, in chunks as without it.
    #[test]
    fn a_spilled_table_is_never_read_again() {
        let dir = tempfile::tempdir().unwrap();
        let (streamed, opened) = changing_table(Some(dir.path()));
        let source = VisSource::Streamed(Arc::new(streamed));
        let held = {
            let reopened = table(10);
            let only = StreamedTable::scan(reopened, Box::new(|| Ok(table(10))), None, &|| false).unwrap().unwrap();
            VisSource::Streamed(Arc::new(only)).read_all().unwrap()
        };
        for _ in 0..2 {
            assert_eq!(chunk_sizes(&source), vec![4, 4, 2]);
            assert_eq!(source.read_all().unwrap(), held);
        }
        assert_eq!(opened.load(std::sync::atomic::Ordering::SeqCst), 1, "the file was opened again");
    }
}
