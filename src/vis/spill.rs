//! A streamed table's samples as its first reading decoded them, kept in an unlinked temporary
//! file for the passes after it ([`Spill`]).
//!
//! Imaging reads a streamed table several times (its summary, the uv density for uniform and
//! Briggs weights, the gridding, each residual update through the operator). Decoding a
//! MeasurementSet's cells or a Parquet file's pages again at every pass cost more than the
//! gridding itself; reading the decoded columns back is a copy. The file is unlinked from the
//! start (nothing is left behind, whatever ends the process), the pages it takes live in the
//! system's page cache rather than in the process, and it is only kept on a disk that has
//! room: not on a RAM-backed file system (tmpfs), never leaving less than [`SPACE_RESERVE`]
//! free. Where it cannot be kept, each pass reads the table again, as before.

use super::data::Visibilities;
use std::fs::File;
use std::io::Write;
use std::path::Path;

/// Free space a spill leaves on its file system, at least: a job does not fill the disk that
/// other programs (and its own products) need.
pub const SPACE_RESERVE: u64 = 2 << 30;

/// Where a table's samples are kept decoded: the system's temporary directory (`TMPDIR`).
pub fn spill_dir() -> std::path::PathBuf {
    std::env::temp_dir()
}

/// Values whose bytes are written and read back as they are in memory: no padding, and every
/// bit pattern is a value.
trait Plain: Copy + Default {}
impl Plain for f64 {}
impl Plain for f32 {}
impl Plain for num_complex::Complex32 {}

fn bytes<T: Plain>(values: &[T]) -> &[u8] {
    // SAFETY: `Plain` types (f64, f32, Complex32: two f32, repr(C)) have no padding, so every
    // byte of the slice is initialised; u8 has alignment 1 and the length is the slice's size.
    unsafe { std::slice::from_raw_parts(values.as_ptr().cast(), std::mem::size_of_val(values)) }
}

fn bytes_mut<T: Plain>(values: &mut [T]) -> &mut [u8] {
    // SAFETY: as `bytes`; and every bit pattern written through the view is a valid `Plain`
    // value, so the slice stays valid whatever is read into it.
    unsafe { std::slice::from_raw_parts_mut(values.as_mut_ptr().cast(), std::mem::size_of_val(values)) }
}

/// One decoded batch in the file: where it starts and its columns' lengths (u, v, w, vis,
/// weight, frequency, imaging weight; frequency and imaging weight may be empty).
#[derive(Clone, Copy, Debug)]
struct Record {
    offset: u64,
    lengths: [usize; 7],
}

/// The decoded samples of a table's first reading, batch after batch.
pub struct Spill {
    file: File,
    records: Vec<Record>,
    bytes: u64,
}

/// Why a table is not spilled, said once in the job's log.
pub type NoSpill = String;

impl Spill {
    /// An empty spill in `dir`, if the file system there is fit for one.
    pub fn create(dir: &Path) -> Result<Spill, NoSpill> {
        let file = tempfile::tempfile_in(dir).map_err(|e| format!("no temporary file could be made in {}: {e}", dir.display()))?;
        if let Some(kind) = ram_backed(&file) {
            return Err(format!("{} is {kind}, held in memory", dir.display()));
        }
        Ok(Spill { file, records: Vec::new(), bytes: 0 })
    }

    /// Bytes written so far.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Appends a decoded batch; an error (the disk short of room, a write failing) means the
    /// spill is incomplete and must be dropped.
    pub fn append(&mut self, vis: &Visibilities) -> Result<(), NoSpill> {
        let parts: [&[u8]; 7] = [
            bytes(&vis.u),
            bytes(&vis.v),
            bytes(&vis.w),
            bytes(&vis.vis),
            bytes(&vis.weight),
            bytes(&vis.frequency),
            bytes(&vis.imaging_weight),
        ];
        let size: u64 = parts.iter().map(|p| p.len() as u64).sum();
        if let Some(free) = free_bytes(&self.file) {
            if free < size.saturating_add(SPACE_RESERVE) {
                return Err(format!(
                    "the disk of the temporary directory has {} free, and a copy of the samples would leave less than {}",
                    crate::limits::format_bytes(free as f64),
                    crate::limits::format_bytes(SPACE_RESERVE as f64)
                ));
            }
        }
        let lengths = [vis.u.len(), vis.v.len(), vis.w.len(), vis.vis.len(), vis.weight.len(), vis.frequency.len(), vis.imaging_weight.len()];
        for part in parts {
            self.file.write_all(part).map_err(|e| format!("writing the temporary copy of the samples failed: {e}"))?;
        }
        self.records.push(Record { offset: self.bytes, lengths });
        self.bytes += size;
        Ok(())
    }

    /// Calls `f` with every sample in the order written, gathered into chunks of at least
    /// `chunk_rows` (the last may be smaller; one batch larger than that is one chunk), read
    /// into one buffer reused for every chunk. A read that fails is an error naming `table`,
    /// the table the samples came from.
    pub fn for_each_chunk(&self, chunk_rows: usize, table: &Path, f: &mut dyn FnMut(&Visibilities) -> crate::Result<()>) -> crate::Result<()> {
        let mut buffer = Visibilities::default();
        for record in &self.records {
            self.read_into(record, &mut buffer)
                .map_err(|e| crate::Error::input(table, format!("reading back the temporary copy of its samples failed: {e}")))?;
            if buffer.len() >= chunk_rows {
                f(&buffer)?;
                buffer.clear();
            }
        }
        if !buffer.is_empty() {
            f(&buffer)?;
        }
        Ok(())
    }

    /// Appends one record's columns to `buffer`.
    fn read_into(&self, record: &Record, buffer: &mut Visibilities) -> std::io::Result<()> {
        let mut offset = record.offset;
        let [nu, nv, nw, nvis, nweight, nfrequency, nimaging] = record.lengths;
        offset = read_column(&self.file, offset, &mut buffer.u, nu)?;
        offset = read_column(&self.file, offset, &mut buffer.v, nv)?;
        offset = read_column(&self.file, offset, &mut buffer.w, nw)?;
        offset = read_column(&self.file, offset, &mut buffer.vis, nvis)?;
        offset = read_column(&self.file, offset, &mut buffer.weight, nweight)?;
        offset = read_column(&self.file, offset, &mut buffer.frequency, nfrequency)?;
        read_column(&self.file, offset, &mut buffer.imaging_weight, nimaging)?;
        Ok(())
    }
}

/// Appends `n` values read at `offset` to `column`; the offset after them.
fn read_column<T: Plain>(file: &File, offset: u64, column: &mut Vec<T>, n: usize) -> std::io::Result<u64> {
    let start = column.len();
    column.resize(start + n, T::default());
    let tail = bytes_mut(&mut column[start..]);
    read_exact_at(file, tail, offset)?;
    Ok(offset + tail.len() as u64)
}

#[cfg(unix)]
fn read_exact_at(file: &File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
    std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
}

#[cfg(not(unix))]
fn read_exact_at(file: &File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
    use std::io::{Read, Seek, SeekFrom};
    let mut f = file.try_clone()?;
    f.seek(SeekFrom::Start(offset))?;
    f.read_exact(buf)
}

/// The file system's name where the file lives in memory (tmpfs, ramfs), if it does.
#[cfg(target_os = "linux")]
fn ram_backed(file: &File) -> Option<&'static str> {
    use std::os::fd::AsRawFd;
    const TMPFS_MAGIC: i64 = 0x0102_1994;
    const RAMFS_MAGIC: i64 = 0x8584_58f6;
    let mut s = std::mem::MaybeUninit::<libc::statfs>::uninit();
    // SAFETY: fstatfs writes a statfs structure to the pointer given, which points to room for
    // one; it is read only if the call succeeded.
    let ok = unsafe { libc::fstatfs(file.as_raw_fd(), s.as_mut_ptr()) } == 0;
    if !ok {
        return None;
    }
    // SAFETY: initialised by the successful call above.
    let kind = unsafe { s.assume_init() }.f_type as i64;
    match kind {
        TMPFS_MAGIC => Some("tmpfs"),
        RAMFS_MAGIC => Some("ramfs"),
        _ => None,
    }
}

#[cfg(not(target_os = "linux"))]
fn ram_backed(_file: &File) -> Option<&'static str> {
    None
}

/// Bytes free to an unprivileged user on the file's file system, where that can be told.
#[cfg(unix)]
fn free_bytes(file: &File) -> Option<u64> {
    use std::os::fd::AsRawFd;
    let mut s = std::mem::MaybeUninit::<libc::statvfs>::uninit();
    // SAFETY: fstatvfs writes a statvfs structure to the pointer given, which points to room
    // for one; it is read only if the call succeeded.
    let ok = unsafe { libc::fstatvfs(file.as_raw_fd(), s.as_mut_ptr()) } == 0;
    if !ok {
        return None;
    }
    // SAFETY: initialised by the successful call above.
    let s = unsafe { s.assume_init() };
    Some((s.f_bavail as u64).saturating_mul(s.f_frsize as u64))
}

#[cfg(not(unix))]
fn free_bytes(_file: &File) -> Option<u64> {
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use num_complex::Complex32;

    fn batch(n: usize, first: usize, with_imaging: bool) -> Visibilities {
        Visibilities {
            u: (0..n).map(|k| (first + k) as f64 * 1.25 + 1e-9).collect(),
            v: (0..n).map(|k| -((first + k) as f64)).collect(),
            w: (0..n).map(|k| (first + k) as f64 / 3.0).collect(),
            vis: (0..n).map(|k| Complex32::new(k as f32, -(first as f32))).collect(),
            weight: (0..n).map(|k| 0.5 + k as f32).collect(),
            frequency: if first == 0 { Vec::new() } else { vec![1.4e9; n] },
            imaging_weight: if with_imaging { vec![2.0; n] } else { Vec::new() },
            ..Visibilities::default()
        }
    }

    /// What is read back is what was written, to the bit, gathered into chunks as asked, and
    /// the same on a second pass.
    #[test]
    fn samples_read_back_as_written_in_chunks() {
        let dir = tempfile::tempdir().unwrap();
        let mut spill = Spill::create(dir.path()).expect("a spill in the temporary directory (not on tmpfs)");
        let batches = [batch(5, 0, false), batch(3, 5, true), batch(4, 8, false)];
        let mut all = Visibilities::default();
        for b in &batches {
            spill.append(b).unwrap();
            all.push_batch(b.clone());
        }
        assert_eq!(spill.bytes(), (12 * (24 + 8 + 4) + 7 * 8 + 3 * 4) as u64);
        for _ in 0..2 {
            let mut read = Visibilities::default();
            let mut sizes = Vec::new();
            spill
                .for_each_chunk(6, Path::new("t"), &mut |c| {
                    sizes.push(c.len());
                    read.push_batch(c.clone());
                    Ok(())
                })
                .unwrap();
            assert_eq!(sizes, vec![8, 4]);
            assert_eq!(read, all);
        }
    }

    /// /dev/shm, tmpfs on Linux, is refused.
    #[cfg(target_os = "linux")]
    #[test]
    fn a_ram_backed_directory_is_refused_naming_it() {
        let e = Spill::create(Path::new("/dev/shm")).err().expect("/dev/shm refused");
        assert!(e.contains("/dev/shm is tmpfs"), "{e}");
    }
}
