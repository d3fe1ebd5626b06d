//! Image files: writing an image with WSClean's layout and keywords, and reading one back
//! (see the module above for the conventions).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use fitsio::errors::Error as FitsioError;
use fitsio::hdu::{FitsHdu, HduInfo};
use fitsio::images::{ImageDescription, ImageType};
use fitsio::FitsFile;

use crate::{Error, Result};

use super::error::{Cfitsio, FitsError, WriteFailure};
use crate::deconv::Beam;

/// Celestial coordinates of an image: where it points and how large its pixels are.
///
/// The reference pixel is always the image centre, pixel (nx/2, ny/2) counted from 0
/// (FITS CRPIX = n/2 + 1), because that is where the imager puts the phase centre; a
/// separate reference pixel would only be a second way of saying the same thing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageWcs {
    /// Right ascension of the phase centre, degrees.
    pub ra_deg: f64,
    /// Declination of the phase centre, degrees.
    pub dec_deg: f64,
    /// Side of a (square) pixel, degrees; positive.
    pub pixel_deg: f64,
    /// Centre frequency of the image, Hz. Without it the file has no FREQ axis.
    pub freq_hz: Option<f64>,
    /// Bandwidth the image covers, Hz (the FREQ axis increment). Needs `freq_hz`.
    pub bandwidth_hz: Option<f64>,
}

/// Brightness unit of the pixels, written as BUNIT.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BrightnessUnit {
    /// `JY/BEAM`: dirty and restored images (flux density per synthesised beam).
    JyPerBeam,
    /// `JY/PIXEL`: model images and the network's estimates (flux density per pixel).
    JyPerPixel,
    /// No unit (an empty BUNIT): ratios such as the uncertainty map.
    Ratio,
}

impl BrightnessUnit {
    /// The BUNIT string, as WSClean spells it.
    pub fn as_fits(self) -> &'static str {
        match self {
            BrightnessUnit::JyPerBeam => "JY/BEAM",
            BrightnessUnit::JyPerPixel => "JY/PIXEL",
            BrightnessUnit::Ratio => "",
        }
    }
}

/// An image read from a FITS file.
#[derive(Debug, Clone, PartialEq)]
pub struct FitsImage {
    /// Pixels, row-major `data[iy * nx + ix]` (FITS storage order), all finite.
    pub data: Vec<f64>,
    /// Length of FITS axis 1 (RA).
    pub nx: usize,
    /// Length of FITS axis 2 (Dec).
    pub ny: usize,
    /// Celestial coordinates, if the header has a RA/Dec SIN or TAN system.
    pub wcs: Option<ImageWcs>,
    /// BUNIT as written in the file, if any.
    pub unit: Option<String>,
}

/// A FITS content error as the crate's error.
fn invalid(path: &Path, message: impl Into<String>) -> Error {
    FitsError::Invalid { path: path.to_path_buf(), message: message.into() }.into()
}

/// A cfitsio failure while `doing` something with `path`, as the crate's error.
fn cfitsio(path: &Path, doing: impl Into<String>, e: FitsioError) -> Error {
    FitsError::Cfitsio { path: path.to_path_buf(), doing: doing.into(), source: Cfitsio(e) }.into()
}

/// cfitsio's status code for "keyword does not exist".
const KEY_NO_EXIST: i32 = 202;

/// The longest string value that fits on one header card ('' quoting included).
const MAX_STRING_VALUE: usize = 68;

/// Keywords this module writes itself or that describe the file structure; extra
/// keywords may not redefine them, or the file would contradict itself.
const RESERVED_KEYWORDS: &[&str] = &[
    "SIMPLE", "BITPIX", "EXTEND", "END", "BSCALE", "BZERO", "BLANK", "BUNIT", "BMAJ", "BMIN", "BPA",
    "EQUINOX", "RADESYS", "RADECSYS", "SPECSYS", "ORIGIN", "LONPOLE", "LATPOLE", "COMMENT",
];

/// The longest HISTORY text an extra keyword may carry (cfitsio continues it over as many
/// cards as it needs).
const MAX_HISTORY: usize = 4096;

/// Keyword families of the coordinate system (CTYPEn, PCi_j, ...), reserved like the above.
const RESERVED_PREFIXES: &[&str] = &["NAXIS", "CTYPE", "CRPIX", "CRVAL", "CDELT", "CUNIT", "CROTA"];

/// The longest suffix a writer appends to a prefix (`job::products` checks its names
/// against it).
pub(crate) const LONGEST_PRODUCT_SUFFIX: &str = "-uncertainty.fits";

/// Bytes in one file name (NAME_MAX of Linux's and macOS's file systems).
pub(crate) const NAME_MAX: usize = 255;

/// Bytes in the longest path cfitsio opens (its FLEN_FILENAME less the terminator).
pub(crate) const CFITSIO_PATH_MAX: usize = 1024;

/// Bytes in the longest path the system opens (Linux's PATH_MAX less the terminator).
pub(crate) const PATH_MAX: usize = 4095;

/// Bytes a [`TempSibling`] adds to its target's name: `.` and `.tmp-<pid>-<counter>`, at
/// their longest (u32 pid, u64 counter).
const TEMP_NAME_EXTRA: usize = 1 + ".tmp-".len() + 10 + 1 + 20;

/// How an output file is written, for [`check_name_length`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum OutputWrite {
    /// Through a temporary beside it.
    Direct,
    /// Through a staging directory beside it (its path absolute), then a temporary.
    Staged,
}

/// Refuses an output file whose name or path, once written through its temporary (and
/// staging directory), is too long for the file system or, for FITS, for cfitsio: found
/// before any work, not as "cfitsio status 105" after it. `shown` names the file the user gave.
pub(crate) fn check_name_length(file: &Path, how: OutputWrite, fits: bool, shown: &str) -> std::result::Result<(), String> {
    let name = file.file_name().map_or(0, |n| n.len());
    if name + TEMP_NAME_EXTRA > NAME_MAX {
        return Err(format!(
            "{shown}: the file name would have {name} bytes, more than the {} allowed ({NAME_MAX}, the file system's limit, less {TEMP_NAME_EXTRA} for the temporary it is written through): use a shorter name",
            NAME_MAX - TEMP_NAME_EXTRA
        ));
    }
    let dir = file.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let dir_len = match how {
        OutputWrite::Staged if !dir.is_absolute() => {
            std::env::current_dir().map_or(0, |cwd| cwd.as_os_str().len() + 1) + dir.as_os_str().len() + crate::staging::STAGED_PATH_EXTRA
        }
        OutputWrite::Staged => dir.as_os_str().len() + crate::staging::STAGED_PATH_EXTRA,
        // `./` before a relative name (`fitsio_path`), `/` after the directory.
        OutputWrite::Direct => dir.as_os_str().len() + 3,
    };
    let (most, whose) = if fits { (CFITSIO_PATH_MAX, "cfitsio takes") } else { (PATH_MAX, "the system takes") };
    let length = dir_len + name + TEMP_NAME_EXTRA;
    if length > most {
        return Err(format!(
            "{shown}: the path written would have up to {length} bytes (with the temporary{} it is written through), more than the {most} {whose}: use a shorter path",
            if how == OutputWrite::Staged { " and staging directory" } else { "" }
        ));
    }
    Ok(())
}

/// `value` as one header card holds it: printable ASCII, each other character written as `?`,
/// and at most [`MAX_STRING_VALUE`] characters with quotes counted twice (cut after that).
/// The second part says what was changed, for a warning: a name read from the data (a
/// telescope, a field) must not lose characters without a word, nor fail the write.
pub(crate) fn header_text(value: &str) -> (String, Option<String>) {
    let printable = |c: char| (' '..='~').contains(&c);
    let replaced = value.chars().filter(|&c| !printable(c)).count();
    let mut text = String::new();
    let mut card_len = 0;
    let mut cut = false;
    for c in value.chars().map(|c| if printable(c) { c } else { '?' }) {
        let len = if c == '\'' { 2 } else { 1 };
        if card_len + len > MAX_STRING_VALUE {
            cut = true;
            break;
        }
        card_len += len;
        text.push(c);
    }
    let mut changes = Vec::new();
    if replaced > 0 {
        changes.push(format!("{replaced} character(s) other than printable ASCII written as '?'"));
    }
    if cut {
        changes.push(format!("cut to {} characters, all one header card holds", text.chars().count()));
    }
    let note = (!changes.is_empty()).then(|| format!("{value:?} is written as {text:?}: FITS header values are printable ASCII ({})", changes.join("; ")));
    (text, note)
}

/// Refuses an output prefix that names no file (`out/`, `.`, `..`): products are named
/// `<prefix>-dirty.fits`, ..., so the prefix must end in a file-name part (`out/obs`); and
/// one whose product names would be too long ([`check_name_length`]).
pub(crate) fn check_output_prefix(prefix: &str) -> std::result::Result<(), String> {
    // A `~` or `$VAR` the shell did not expand (quoted, or from a YAML file) would make a
    // directory literally named `~` or `$HOME`, which a later `rm -rf ~` turns into a disaster.
    let unexpanded = prefix.starts_with('~') || prefix.split(['/', std::path::MAIN_SEPARATOR]).any(|part| {
        part.strip_prefix('$').is_some_and(|rest| rest.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_' || c == '{'))
    });
    if unexpanded {
        return Err(format!("\"{prefix}\" holds a `~` or `$VARIABLE` that no shell expanded (r2d2 does not expand them): give the path as it is, e.g. /data/out/obs"));
    }
    let last = prefix.rsplit(['/', std::path::MAIN_SEPARATOR]).next().unwrap_or_default();
    if last.trim().is_empty() || last == "." || last == ".." {
        return Err(format!("\"{prefix}\" names a directory, not a file name: products are named <prefix>-dirty.fits, ..., so end the prefix with a name (out/obs, say)"));
    }
    let longest = PathBuf::from(format!("{prefix}{LONGEST_PRODUCT_SUFFIX}"));
    check_name_length(&longest, OutputWrite::Staged, true, &format!("prefix \"{prefix}\" (products such as <prefix>{LONGEST_PRODUCT_SUFFIX})"))
}

/// Refuses an output file path that names no file (`out/`, an existing directory) or whose
/// name is too long ([`check_name_length`], written directly), before any work.
pub(crate) fn check_output_file(path: &Path, fits: bool) -> std::result::Result<(), String> {
    let shown = path.display().to_string();
    let text = path.as_os_str().to_string_lossy();
    let last = text.rsplit(['/', std::path::MAIN_SEPARATOR]).next().unwrap_or_default();
    if last.trim().is_empty() || last == "." || last == ".." {
        return Err(format!("\"{shown}\" names a directory, not a file: give the file to write (out/obs.parquet, say)"));
    }
    if path.is_dir() {
        return Err(format!("\"{shown}\" is a directory: give the file to write in it (\"{}\", say)", path.join("obs.parquet").display()));
    }
    check_name_length(path, OutputWrite::Direct, fits, &format!("\"{shown}\""))
}

/// Writes a 2-D sky image as a WSClean-style FITS file, replacing `path` atomically.
///
/// The file gets axes RA, Dec, FREQ (only when `wcs.freq_hz` is known: a made-up
/// frequency would be worse than none) and STOKES (I), float32 pixels, the celestial
/// WCS, BUNIT, the beam if given, and the `extra` keywords; values of `extra` that parse
/// as numbers are written as numbers, others as strings. Pixels must be finite, unless given
/// as [`Pixels::blanked`] (NaN allowed).
///
/// Nothing is ever left half-written at `path`: the file is written to a temporary
/// sibling and renamed over the target, and the temporary is removed on failure.
/// Header floats are written by cfitsio with 15 significant digits (as in WSClean's
/// files); the `EXTNAME = '_PRIMARY'` fitsio adds to the primary HDU is removed.
#[allow(clippy::too_many_arguments)]
pub fn write_image<'a>(
    path: &Path,
    image: impl Into<Pixels<'a>>,
    nx: usize,
    ny: usize,
    wcs: &ImageWcs,
    unit: BrightnessUnit,
    beam: Option<&Beam>,
    extra: &[(&str, String)],
) -> Result<()> {
    write_planes(path, image.into(), nx, ny, 1, wcs, unit, beam, extra)
}

/// Writes `planes` images of `nx x ny` pixels (plane after plane in `cube`) as a FITS cube
/// whose FREQ axis runs over them: `wcs.freq_hz` is the first plane's frequency and
/// `wcs.bandwidth_hz` the step from plane to plane (CDELT3). Otherwise as [`write_image`].
#[allow(clippy::too_many_arguments)]
pub(crate) fn write_cube(
    path: &Path,
    cube: &[f64],
    nx: usize,
    ny: usize,
    planes: usize,
    wcs: &ImageWcs,
    unit: BrightnessUnit,
    beam: Option<&Beam>,
    extra: &[(&str, String)],
) -> Result<()> {
    if wcs.freq_hz.is_none() || wcs.bandwidth_hz.is_none() {
        return Err(Error::parameter("wcs", "a cube needs its first plane's frequency and the step between planes"));
    }
    write_planes(path, cube.into(), nx, ny, planes, wcs, unit, beam, extra)
}

#[allow(clippy::too_many_arguments)]
fn write_planes(
    path: &Path,
    image: Pixels<'_>,
    nx: usize,
    ny: usize,
    planes: usize,
    wcs: &ImageWcs,
    unit: BrightnessUnit,
    beam: Option<&Beam>,
    extra: &[(&str, String)],
) -> Result<()> {
    let Pixels { values: image, blanks } = image;
    check_shape(image.len(), nx, ny.checked_mul(planes).unwrap_or(0))?;
    check_wcs(wcs)?;
    if let Some(beam) = beam {
        check_beam(beam)?;
    }
    let extra =
        extra.iter().map(|(name, value)| ExtraKeyword::parse(name, value)).collect::<Result<Vec<_>>>()?;
    let pixels = to_float32(image, blanks)?;

    let tmp = TempSibling::new(path)?;
    let tmp_name = fitsio_path(tmp.path())?;
    let header = Header { nx, ny, planes, wcs, unit, beam, extra: &extra };
    write_fits(&tmp_name, &pixels, &header).map_err(|e| {
        let disk = why_unwritable(path);
        let kind = disk.as_ref().map_or(std::io::ErrorKind::Other, std::io::Error::kind);
        Error::io(path, std::io::Error::new(kind, WriteFailure { cfitsio: Cfitsio(e), disk }))
    })?;
    // cfitsio reports errors of its final flush nowhere (fitsio closes files in Drop),
    // so check that the whole data unit reached the file before publishing it.
    check_written_size(tmp.path(), path, pixels.len())?;
    tmp.persist()
}

/// Reads the image in the primary HDU of a FITS file.
///
/// Accepts 2, 3 or 4 axes, where axes beyond the second must have length 1 (one plane),
/// and any BITPIX (BSCALE/BZERO applied). The celestial WCS is read if CTYPE1/CTYPE2 are
/// RA---SIN/DEC--SIN or RA---TAN/DEC--TAN (only SIN is ever written; TAN is read as if
/// it were SIN, which agrees near the phase centre); it must have square pixels, RA
/// increasing to the left, no rotation and the reference pixel at the image centre, as
/// `ImageWcs` describes nothing else. Without CTYPE1/CTYPE2 `wcs` is `None`. Any
/// non-finite or blank pixel is an error: sky images must be finite. A gzip-compressed file
/// (`.fits.gz`) is read through a decompressed temporary copy, its size bounded by the memory
/// budget as it is decompressed.
pub fn read_image(path: &Path) -> Result<FitsImage> {
    read_image_within(path, crate::limits::memory_budget())
}

/// [`read_image`], a gzip-compressed file decompressing to at most `budget`.
fn read_image_within(path: &Path, budget: crate::limits::MemoryBudget) -> Result<FitsImage> {
    let metadata = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    if !metadata.is_file() {
        return Err(FitsError::Unusable { path: path.to_path_buf(), message: "not a regular file (expected a FITS image)" }.into());
    }
    // cfitsio would decompress a gzip file whole into memory, whatever size it declares.
    let decompressed = gunzipped(path, budget)?;
    let (source, file_bytes) = match &decompressed {
        Some(copy) => (copy.path(), copy.as_file().metadata().map_err(|e| Error::io(path, e))?.len()),
        None => (path, metadata.len()),
    };
    let mut file = open_literally(source)?;
    let hdu = file.primary_hdu().map_err(|e| cfitsio(path, "cannot read the primary HDU", e))?;
    let (shape, image_type) = match &hdu.info {
        HduInfo::ImageInfo { shape, image_type } => (shape.clone(), *image_type),
        _ => return Err(invalid(path, "the primary HDU is not an image")),
    };
    // fitsio lists axes slowest first; reverse to FITS numbering (axes[0] is NAXIS1).
    let axes: Vec<usize> = shape.iter().rev().copied().collect();
    if !(2..=4).contains(&axes.len()) {
        return Err(invalid(
            path,
            format!("the primary HDU has NAXIS = {}; expected an image with 2, 3 or 4 axes", axes.len()),
        ));
    }
    for (k, &len) in axes.iter().enumerate().skip(2) {
        if len != 1 {
            return Err(invalid(
                path,
                format!(
                    "NAXIS{} = {len}: only single-plane images are supported (axes beyond the second must have length 1)",
                    k + 1
                ),
            ));
        }
    }
    let (nx, ny) = (axes[0], axes[1]);
    if nx == 0 || ny == 0 {
        return Err(invalid(path, format!("NAXIS1 = {nx}, NAXIS2 = {ny}: the image is empty")));
    }
    // A damaged header can declare any size; refuse sizes the file cannot hold before
    // fitsio allocates a buffer for them. The pixels are stored as BITPIX says: `image_type`
    // is what they mean once scaled (BITPIX 16 with a BSCALE of 0.01 is float).
    let stored = stored_bytes_per_pixel(&mut file, &hdu, path)?;
    let data_bytes = nx.checked_mul(ny).and_then(|n| n.checked_mul(stored));
    if data_bytes.is_none_or(|bytes| bytes as u64 > file_bytes) {
        let compressed = if decompressed.is_some() { " once decompressed" } else { "" };
        return Err(invalid(
            path,
            format!("NAXIS1 x NAXIS2 = {nx} x {ny} pixels of {stored} bytes (BITPIX) do not fit in the file's {file_bytes} bytes{compressed}: is it truncated?"),
        ));
    }
    // A size the file holds may still be more than the machine can: refused before the
    // pixels (read as f64, beside cfitsio's buffer of their scaled type) are allocated.
    let needed = (nx * ny) as f64 * (8 + bytes_per_pixel(image_type)) as f64;
    crate::limits::check_memory(needed, &format!("reading its {nx} x {ny} pixels")).map_err(|m| invalid(path, m))?;
    let data: Vec<f64> = hdu.read_image(&mut file).map_err(|e| cfitsio(path, "cannot read the pixels", e))?;
    if data.len() != nx * ny {
        return Err(invalid(
            path,
            format!("read {} pixels but NAXIS1 x NAXIS2 = {nx} x {ny}", data.len()),
        ));
    }

    let mut header = HeaderReader { file: &mut file, hdu: &hdu, path };
    let blank = match image_type {
        ImageType::Float | ImageType::Double => None,
        _ => header.blank_value()?,
    };
    let bad = data.iter().filter(|v| !v.is_finite() || Some(**v) == blank).count();
    if bad > 0 {
        return Err(invalid(
            path,
            format!(
                "{bad} of {} pixels are not finite (NaN, infinite or BLANK); sky images must be finite",
                data.len()
            ),
        ));
    }
    let unit = header.string("BUNIT")?.filter(|u| !u.is_empty());
    let wcs = read_wcs(&mut header, nx, ny, axes.len())?;
    Ok(FitsImage { data, nx, ny, wcs, unit })
}

/// Bytes per pixel as stored in the file: BITPIX / 8 in absolute value.
fn stored_bytes_per_pixel(file: &mut FitsFile, hdu: &FitsHdu, path: &Path) -> Result<usize> {
    let bitpix = hdu.read_key::<i64>(file, "BITPIX").map_err(|e| cfitsio(path, "cannot read BITPIX", e))?;
    match bitpix {
        8 | 16 | 32 | 64 | -32 | -64 => Ok(bitpix.unsigned_abs() as usize / 8),
        other => Err(invalid(path, format!("BITPIX = {other}: expected 8, 16, 32, 64, -32 or -64"))),
    }
}

/// The gzip-compressed file at `path` decompressed into a temporary file, when it is one
/// (`None` otherwise), refused once it passes `budget`: its own trailer's size is not trusted
/// (it is the size modulo 4 GiB, and may lie).
fn gunzipped(path: &Path, budget: crate::limits::MemoryBudget) -> Result<Option<tempfile::NamedTempFile>> {
    use std::io::{Read, Write};
    let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut magic = [0u8; 2];
    let got = file.read(&mut magic).map_err(|e| Error::io(path, e))?;
    if got < 2 || magic != [0x1f, 0x8b] {
        return Ok(None);
    }
    let copy = tempfile::Builder::new().prefix(".r2d2-gunzip-").tempfile().map_err(|e| Error::io(std::env::temp_dir(), e))?;
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut decoder = flate2::read::MultiGzDecoder::new(std::io::BufReader::new(file)).take(budget.bytes.saturating_add(1));
    let mut writer = std::io::BufWriter::new(copy.as_file());
    let written = std::io::copy(&mut decoder, &mut writer).map_err(|e| match e.kind() {
        std::io::ErrorKind::InvalidInput | std::io::ErrorKind::InvalidData | std::io::ErrorKind::UnexpectedEof => {
            invalid(path, format!("gzip-compressed, but it does not decompress: {e}"))
        }
        _ => Error::io(copy.path(), e),
    })?;
    writer.flush().map_err(|e| Error::io(copy.path(), e))?;
    drop(writer);
    if written > budget.bytes {
        return Err(invalid(path, format!("gzip-compressed, and it decompresses to more than {budget}: expected a FITS image whose pixels fit in memory")));
    }
    Ok(Some(copy))
}

/// Bytes per pixel of an image type (what cfitsio reads the pixels as).
fn bytes_per_pixel(image_type: ImageType) -> usize {
    match image_type {
        ImageType::UnsignedByte | ImageType::Byte => 1,
        ImageType::Short | ImageType::UnsignedShort => 2,
        ImageType::Long | ImageType::UnsignedLong | ImageType::Float => 4,
        ImageType::LongLong | ImageType::Double => 8,
    }
}

/// What `write_fits` puts in the header besides the structural keywords.
struct Header<'a> {
    nx: usize,
    ny: usize,
    /// Planes along the FREQ axis (1: an image).
    planes: usize,
    wcs: &'a ImageWcs,
    unit: BrightnessUnit,
    beam: Option<&'a Beam>,
    extra: &'a [ExtraKeyword],
}

/// Creates the FITS file at `file_name` (a cfitsio file name) and writes header and pixels.
/// fitsio names the primary HDU `EXTNAME = '_PRIMARY'` (its own marker); WSClean's files
/// carry no EXTNAME there, and viewers show it as if it were the image's name.
fn remove_primary_extname(file: &mut FitsFile) -> fitsio::errors::Result<()> {
    let mut status = 0;
    // SAFETY: `file` is open and exclusively borrowed for the call, so its raw pointer is valid
    // and used by nothing else; the key name is a NUL-terminated literal; cfitsio reports
    // through `status` only.
    unsafe {
        fitsio::sys::ffdkey(file.as_raw(), c"EXTNAME".as_ptr(), &mut status);
    }
    // 202: no such keyword (a cfitsio that does not add it); nothing to remove.
    match status {
        0 | 202 => Ok(()),
        _ => Err(fitsio::errors::Error::Message(format!("cfitsio status {status} removing EXTNAME"))),
    }
}

/// A HISTORY record (cfitsio continues a long one over several cards).
fn write_history(file: &mut FitsFile, text: &str) -> fitsio::errors::Result<()> {
    let text = std::ffi::CString::new(text).map_err(|_| fitsio::errors::Error::Message("HISTORY text with a NUL byte".into()))?;
    let mut status = 0;
    // SAFETY: `file` is open and exclusively borrowed for the call, so its raw pointer is valid
    // and used by nothing else; `text` is a NUL-terminated string that outlives the call, which
    // cfitsio only reads; it reports through `status` only.
    unsafe {
        fitsio::sys::ffphis(file.as_raw(), text.as_ptr(), &mut status);
    }
    match status {
        0 => Ok(()),
        _ => Err(fitsio::errors::Error::Message(format!("cfitsio status {status} writing HISTORY"))),
    }
}

fn write_fits(file_name: &str, pixels: &[f32], h: &Header) -> fitsio::errors::Result<()> {
    // fitsio takes the shape slowest axis first: [STOKES, FREQ, Dec, RA].
    let dimensions: Vec<usize> =
        if h.wcs.freq_hz.is_some() { vec![1, h.planes, h.ny, h.nx] } else { vec![1, h.ny, h.nx] };
    let description = ImageDescription { data_type: ImageType::Float, dimensions: &dimensions };
    let mut file = FitsFile::create(file_name).with_custom_primary(&description).overwrite().open()?;
    let hdu = file.primary_hdu()?;
    remove_primary_extname(&mut file)?;
    let f = &mut file;

    hdu.write_key(f, "BUNIT", h.unit.as_fits())?;
    // What the pixels are, as CASA's images say it (viewers label the axis with it).
    if h.unit != BrightnessUnit::Ratio {
        hdu.write_key(f, "BTYPE", "Intensity")?;
    }
    if let Some(beam) = h.beam {
        hdu.write_key(f, "BMAJ", (beam.major_deg, "[deg] restoring beam major axis FWHM"))?;
        hdu.write_key(f, "BMIN", (beam.minor_deg, "[deg] restoring beam minor axis FWHM"))?;
        hdu.write_key(f, "BPA", (beam.pa_deg, "[deg] restoring beam position angle"))?;
    }
    hdu.write_key(f, "EQUINOX", 2000.0f64)?;
    hdu.write_key(f, "RADESYS", "FK5")?;
    if h.wcs.freq_hz.is_some() {
        hdu.write_key(f, "SPECSYS", "TOPOCENT")?;
    }
    hdu.write_key(f, "ORIGIN", "r2d2-imaging")?;

    // Reference pixel at the image centre (1-based n/2 + 1), as WSClean does.
    let pixel = h.wcs.pixel_deg;
    hdu.write_key(f, "CTYPE1", "RA---SIN")?;
    hdu.write_key(f, "CRPIX1", (h.nx / 2 + 1) as f64)?;
    hdu.write_key(f, "CRVAL1", (h.wcs.ra_deg, "[deg] phase centre right ascension"))?;
    hdu.write_key(f, "CDELT1", (-pixel, "[deg] RA increases to the left"))?;
    hdu.write_key(f, "CUNIT1", "deg")?;
    hdu.write_key(f, "CTYPE2", "DEC--SIN")?;
    hdu.write_key(f, "CRPIX2", (h.ny / 2 + 1) as f64)?;
    hdu.write_key(f, "CRVAL2", (h.wcs.dec_deg, "[deg] phase centre declination"))?;
    hdu.write_key(f, "CDELT2", pixel)?;
    hdu.write_key(f, "CUNIT2", "deg")?;
    let stokes_axis = match h.wcs.freq_hz {
        Some(freq) => {
            hdu.write_key(f, "CTYPE3", "FREQ")?;
            hdu.write_key(f, "CRPIX3", 1.0f64)?;
            hdu.write_key(f, "CRVAL3", freq)?;
            // WSClean (its -predict) requires CDELT3: an unknown bandwidth is written as the
            // FITS default, 1, which this module reads back as unknown.
            match h.wcs.bandwidth_hz {
                Some(step) if h.planes > 1 => hdu.write_key(f, "CDELT3", (step, "[Hz] from plane to plane"))?,
                Some(bandwidth) => hdu.write_key(f, "CDELT3", (bandwidth, "[Hz] bandwidth"))?,
                None => hdu.write_key(f, "CDELT3", (UNKNOWN_BANDWIDTH, "bandwidth unknown (the FITS default)"))?,
            }
            hdu.write_key(f, "CUNIT3", "Hz")?;
            4
        }
        None => 3,
    };
    hdu.write_key(f, &format!("CTYPE{stokes_axis}"), "STOKES")?;
    hdu.write_key(f, &format!("CRPIX{stokes_axis}"), 1.0f64)?;
    hdu.write_key(f, &format!("CRVAL{stokes_axis}"), (1.0f64, "Stokes I"))?;
    hdu.write_key(f, &format!("CDELT{stokes_axis}"), 1.0f64)?;

    for keyword in h.extra {
        match &keyword.value {
            ExtraValue::Integer(v) => hdu.write_key(f, &keyword.name, *v)?,
            ExtraValue::Float(v) => hdu.write_key(f, &keyword.name, *v)?,
            ExtraValue::Text(v) => hdu.write_key(f, &keyword.name, v.as_str())?,
            ExtraValue::History(text) => write_history(f, text)?,
        }
    }
    hdu.write_image(f, pixels)?;
    Ok(())
}

/// An extra header keyword, checked and typed before anything is written.
struct ExtraKeyword {
    name: String,
    value: ExtraValue,
}

enum ExtraValue {
    Integer(i64),
    Float(f64),
    Text(String),
    /// `HISTORY` text: commentary cards, as many as there are such keywords.
    History(String),
}

impl ExtraKeyword {
    fn parse(name: &str, value: &str) -> Result<Self> {
        let upper = name.to_ascii_uppercase();
        let parameter = || format!("FITS keyword {name:?}");
        let valid_name = !upper.is_empty()
            && upper.len() <= 8
            && upper.bytes().all(|b| b.is_ascii_uppercase() || b.is_ascii_digit() || b == b'-' || b == b'_');
        if !valid_name {
            return Err(Error::parameter(
                parameter(),
                "keyword names must have 1 to 8 characters from A-Z, 0-9, '-' and '_'",
            ));
        }
        let is_wcs_matrix = ["PC", "CD", "PV"].iter().any(|p| {
            upper.strip_prefix(p).is_some_and(|rest| rest.starts_with(|c: char| c.is_ascii_digit()))
        });
        if RESERVED_KEYWORDS.contains(&upper.as_str())
            || RESERVED_PREFIXES.iter().any(|p| upper.starts_with(p))
            || is_wcs_matrix
        {
            return Err(Error::parameter(
                parameter(),
                "is part of the image structure or coordinates written by r2d2-imaging; use another name",
            ));
        }
        let trimmed = value.trim();
        if upper == "HISTORY" {
            if !value.bytes().all(|b| (b' '..=b'~').contains(&b)) || value.len() > MAX_HISTORY {
                return Err(Error::parameter(parameter(), format!("HISTORY text must be printable ASCII of at most {MAX_HISTORY} characters")));
            }
            return Ok(ExtraKeyword { name: upper, value: ExtraValue::History(value.to_string()) });
        }
        let value = if let Ok(v) = trimmed.parse::<i64>() {
            ExtraValue::Integer(v)
        } else if let Some(v) = trimmed.parse::<f64>().ok().filter(|v| v.is_finite()) {
            ExtraValue::Float(v)
        } else {
            // Quotes are doubled on the card, so they count twice.
            let card_len = value.len() + value.matches('\'').count();
            if !value.bytes().all(|b| (b' '..=b'~').contains(&b)) || card_len > MAX_STRING_VALUE {
                return Err(Error::parameter(
                    parameter(),
                    format!(
                        "string values must be printable ASCII of at most {MAX_STRING_VALUE} characters, got {value:?}"
                    ),
                ));
            }
            ExtraValue::Text(value.to_string())
        };
        Ok(ExtraKeyword { name: upper, value })
    }
}

fn check_shape(len: usize, nx: usize, ny: usize) -> Result<()> {
    if nx == 0 || ny == 0 {
        return Err(Error::parameter("image size", format!("nx = {nx}, ny = {ny}: both must be at least 1")));
    }
    match nx.checked_mul(ny) {
        Some(n) if n == len => Ok(()),
        _ => Err(Error::parameter("image", format!("has {len} pixels but nx x ny = {nx} x {ny}"))),
    }
}

fn check_wcs(wcs: &ImageWcs) -> Result<()> {
    if !wcs.ra_deg.is_finite() {
        return Err(Error::parameter("wcs.ra_deg", format!("{}: must be finite", wcs.ra_deg)));
    }
    if !(-90.0..=90.0).contains(&wcs.dec_deg) {
        return Err(Error::parameter("wcs.dec_deg", format!("{}: must be within [-90, 90]", wcs.dec_deg)));
    }
    if !(wcs.pixel_deg.is_finite() && wcs.pixel_deg > 0.0) {
        return Err(Error::parameter("wcs.pixel_deg", format!("{}: must be positive", wcs.pixel_deg)));
    }
    for (name, value) in [("wcs.freq_hz", wcs.freq_hz), ("wcs.bandwidth_hz", wcs.bandwidth_hz)] {
        if let Some(v) = value.filter(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(Error::parameter(name, format!("{v}: must be positive")));
        }
    }
    if wcs.bandwidth_hz.is_some() && wcs.freq_hz.is_none() {
        return Err(Error::parameter(
            "wcs.bandwidth_hz",
            "given without wcs.freq_hz; the FREQ axis that would carry it needs a frequency",
        ));
    }
    Ok(())
}

fn check_beam(beam: &Beam) -> Result<()> {
    for (name, v) in [("beam.major_deg", beam.major_deg), ("beam.minor_deg", beam.minor_deg)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(Error::parameter(name, format!("{v}: must be positive")));
        }
    }
    if beam.minor_deg > beam.major_deg {
        return Err(Error::parameter(
            "beam.minor_deg",
            format!("{} is larger than beam.major_deg = {}", beam.minor_deg, beam.major_deg),
        ));
    }
    if !beam.pa_deg.is_finite() {
        return Err(Error::parameter("beam.pa_deg", format!("{}: must be finite", beam.pa_deg)));
    }
    Ok(())
}

/// The pixels [`write_image`] writes: finite (a slice, a vector or an array of `f64`), or
/// with blanks allowed ([`Pixels::blanked`]).
#[derive(Clone, Copy, Debug)]
pub struct Pixels<'a> {
    values: &'a [f64],
    blanks: bool,
}

impl<'a> Pixels<'a> {
    /// Pixels that may be blank (NaN, the blank of float FITS images): a primary-beam
    /// corrected image where the beam is below its cut. Infinite values are refused still.
    pub fn blanked(values: &'a [f64]) -> Pixels<'a> {
        Pixels { values, blanks: true }
    }
}

impl<'a> From<&'a [f64]> for Pixels<'a> {
    fn from(values: &'a [f64]) -> Self {
        Pixels { values, blanks: false }
    }
}

impl<'a> From<&'a Vec<f64>> for Pixels<'a> {
    fn from(values: &'a Vec<f64>) -> Self {
        Pixels { values, blanks: false }
    }
}

impl<'a, const N: usize> From<&'a [f64; N]> for Pixels<'a> {
    fn from(values: &'a [f64; N]) -> Self {
        Pixels { values, blanks: false }
    }
}

/// Converts to the float32 the file stores, refusing values float32 cannot hold (and NaN,
/// unless blanks are allowed).
fn to_float32(image: &[f64], blanks: bool) -> Result<Vec<f32>> {
    let pixels: Vec<f32> = image.iter().map(|&v| v as f32).collect();
    let bad = pixels.iter().filter(|v| !(v.is_finite() || (blanks && v.is_nan()))).count();
    if bad > 0 {
        return Err(Error::parameter(
            "image",
            format!(
                "{bad} of {} pixels are not finite or exceed the float32 range; sky images must be finite",
                pixels.len()
            ),
        ));
    }
    Ok(pixels)
}

/// Opens `path` read-only, its name taken as it is: cfitsio's `fits_open_file` parses names
/// (`[1]` selects an extension, `-` is standard input, `mem://` a driver), so a product named
/// `a[1]-dirty.fits`, which the writer makes, could not be read back; `fits_open_diskfile` opens
/// the file of that name.
fn open_literally(path: &Path) -> Result<FitsFile> {
    let unusable = |message| Error::from(FitsError::Unusable { path: path.to_path_buf(), message });
    let name = path.to_str().ok_or_else(|| unusable("the file name is not valid UTF-8, which cfitsio requires"))?;
    let name = std::ffi::CString::new(name).map_err(|_| unusable("the file name holds a NUL byte"))?;
    let mut fptr = std::ptr::null_mut();
    let mut status = 0;
    // SAFETY: `name` is a NUL-terminated string that outlives the call, and `fptr` and
    // `status` are valid for writes; ffdkopn reads the name and writes only those two.
    unsafe { fitsio::sys::ffdkopn(&mut fptr, name.as_ptr(), fitsio::FileOpenMode::READONLY as std::os::raw::c_int, &mut status) };
    fitsio::errors::check_status(status).map_err(|e| cfitsio(path, "cannot open as FITS", e))?;
    // SAFETY: status 0: ffdkopn opened the file and `fptr` is its only handle, handed to the
    // FitsFile, which closes it once, when dropped.
    unsafe { FitsFile::from_raw(fptr, fitsio::FileOpenMode::READONLY) }.map_err(|e| cfitsio(path, "cannot open as FITS", e))
}

/// The file name to hand to cfitsio for `path` (a temporary the writer names itself).
///
/// cfitsio parses file names: `-` is stdin, a leading `!` means overwrite, `mem://` and
/// `http://` select drivers, `[...]` selects extensions. A `./` in front of relative paths
/// disarms the prefixes; brackets cannot be escaped, so such names are refused.
fn fitsio_path(path: &Path) -> Result<String> {
    let unusable = |message| Error::from(FitsError::Unusable { path: path.to_path_buf(), message });
    let name = path.to_str().ok_or_else(|| unusable("the file name is not valid UTF-8, which cfitsio requires"))?;
    if name.contains('[') {
        return Err(unusable("file names containing '[' are not supported (cfitsio reads them as extension selectors)"));
    }
    Ok(if path.is_absolute() { name.to_string() } else { format!("./{name}") })
}

/// Why the directory of `path` takes no more data, in the system's words (`No space left on
/// device`), found by writing a small probe file there: cfitsio reports only its own status
/// (105, 106), which says nothing of the cause. `None` when the probe goes through.
fn why_unwritable(path: &Path) -> Option<std::io::Error> {
    use std::io::Write;
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let probe = tempfile::tempfile_in(dir).and_then(|mut f| {
        f.write_all(&[0u8; 4096])?;
        f.sync_all()
    });
    probe.err()
}

/// Checks that the file is as long as header plus data unit: one header block at least,
/// the data padded to whole 2880-byte blocks, nothing partial.
fn check_written_size(written: &Path, target: &Path, n_pixels: usize) -> Result<()> {
    const BLOCK: u64 = 2880;
    let len = std::fs::metadata(written).map_err(|e| Error::io(target, e))?.len();
    let data_bytes = (n_pixels as u64 * 4).div_ceil(BLOCK) * BLOCK;
    if len % BLOCK != 0 || len < BLOCK + data_bytes {
        return Err(Error::io(
            target,
            std::io::Error::other(format!(
                "the FITS file came out {len} bytes long, too short for {n_pixels} float32 pixels (disk full?)"
            )),
        ));
    }
    Ok(())
}

/// A temporary file next to an output file; removed when dropped unless persisted.
/// Shared with `vis`, whose outputs follow the same never-partial rule.
///
/// Same directory, so that the final rename is atomic and never crosses file systems;
/// process id and a counter in the name, so that concurrent writers do not collide.
pub(crate) struct TempSibling {
    tmp: PathBuf,
    target: PathBuf,
    persisted: bool,
}

impl TempSibling {
    pub(crate) fn new(target: &Path) -> Result<Self> {
        static COUNTER: AtomicU64 = AtomicU64::new(0);
        let name = target
            .file_name()
            .ok_or_else(|| Error::input(target, "the output path does not end in a file name"))?;
        // Only harmless characters, whatever the target name holds (cfitsio parses names).
        let safe: String = name
            .to_string_lossy()
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') { c } else { '_' })
            .collect();
        let tmp_name =
            format!(".{safe}.tmp-{}-{}", std::process::id(), COUNTER.fetch_add(1, Ordering::Relaxed));
        Ok(TempSibling {
            tmp: target.with_file_name(tmp_name),
            target: target.to_path_buf(),
            persisted: false,
        })
    }

    pub(crate) fn path(&self) -> &Path {
        &self.tmp
    }

    /// Flushes the temporary to disk and renames it over the target.
    pub(crate) fn persist(mut self) -> Result<()> {
        std::fs::File::open(&self.tmp).and_then(|f| f.sync_all()).map_err(|e| Error::io(&self.target, e))?;
        std::fs::rename(&self.tmp, &self.target).map_err(|e| Error::io(&self.target, e))?;
        self.persisted = true;
        Ok(())
    }
}

impl Drop for TempSibling {
    fn drop(&mut self) {
        if !self.persisted {
            // The temporary may not exist yet; nothing useful to do if removal fails.
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Header access of one HDU with errors that name the file and the keyword.
struct HeaderReader<'a> {
    file: &'a mut FitsFile,
    hdu: &'a FitsHdu,
    path: &'a Path,
}

impl HeaderReader<'_> {
    /// A numeric keyword; `None` if absent, an error if present but not a finite number.
    fn f64(&mut self, name: &str) -> Result<Option<f64>> {
        match self.hdu.read_key::<f64>(self.file, name) {
            Ok(v) if v.is_finite() => Ok(Some(v)),
            Ok(v) => Err(invalid(self.path, format!("header keyword {name} = {v}: expected a finite number"))),
            Err(FitsioError::Fits(e)) if e.status == KEY_NO_EXIST => Ok(None),
            Err(e) => Err(cfitsio(self.path, format!("header keyword {name}: expected a number"), e)),
        }
    }

    /// A numeric keyword that must be present; `why` says what needs it.
    fn require_f64(&mut self, name: &str, why: &str) -> Result<f64> {
        self.f64(name)?.ok_or_else(|| {
            invalid(self.path, format!("header keyword {name} is missing; {why} needs it"))
        })
    }

    /// A keyword's value as text, trimmed; `None` if absent.
    fn string(&mut self, name: &str) -> Result<Option<String>> {
        match self.hdu.read_key::<String>(self.file, name) {
            Ok(v) => Ok(Some(v.trim().to_string())),
            Err(FitsioError::Fits(e)) if e.status == KEY_NO_EXIST => Ok(None),
            Err(e) => Err(cfitsio(self.path, format!("header keyword {name}"), e)),
        }
    }

    /// The value cfitsio returns for BLANK pixels of an integer image (it scales them
    /// like any other pixel when no null value is requested).
    fn blank_value(&mut self) -> Result<Option<f64>> {
        let Some(blank) = self.f64("BLANK")? else {
            return Ok(None);
        };
        let scale = self.f64("BSCALE")?.unwrap_or(1.0);
        let zero = self.f64("BZERO")?.unwrap_or(0.0);
        Ok(Some(blank * scale + zero))
    }
}

/// Reads the celestial coordinate system and the frequency of a single-plane image.
fn read_wcs(h: &mut HeaderReader, nx: usize, ny: usize, naxis: usize) -> Result<Option<ImageWcs>> {
    let path = h.path;
    let ctype1 = h.string("CTYPE1")?;
    let ctype2 = h.string("CTYPE2")?;
    if ctype1.is_none() && ctype2.is_none() {
        return Ok(None);
    }
    let (ctype1, ctype2) = (ctype1.unwrap_or_default(), ctype2.unwrap_or_default());
    match (ctype1.to_ascii_uppercase().as_str(), ctype2.to_ascii_uppercase().as_str()) {
        ("RA---SIN", "DEC--SIN") => {}
        ("RA---TAN", "DEC--TAN") => log::warn!(
            "{}: TAN projection read as SIN; positions differ away from the phase centre",
            path.display()
        ),
        _ => {
            return Err(invalid(
                path,
                format!(
                    "CTYPE1 = '{ctype1}', CTYPE2 = '{ctype2}': expected 'RA---SIN' and 'DEC--SIN' \
                     (or 'RA---TAN' and 'DEC--TAN'); other axes and projections are not supported"
                ),
            ))
        }
    }
    for axis in ["CUNIT1", "CUNIT2"] {
        if let Some(unit) = h.string(axis)?.filter(|u| !u.eq_ignore_ascii_case("deg")) {
            return Err(invalid(path, format!("{axis} = '{unit}': expected 'deg'")));
        }
    }
    if let Some(frame) =
        h.string("RADESYS")?.filter(|f| !["FK5", "ICRS"].contains(&f.to_ascii_uppercase().as_str()))
    {
        return Err(invalid(path, format!("RADESYS = '{frame}': expected 'FK5' or 'ICRS'")));
    }
    if let Some(equinox) = h.f64("EQUINOX")?.filter(|e| *e != 2000.0) {
        return Err(invalid(path, format!("EQUINOX = {equinox}: expected 2000")));
    }
    // Rotations and generalised projections, which ImageWcs cannot describe.
    for (key, default) in [
        ("CROTA1", 0.0),
        ("CROTA2", 0.0),
        ("PC1_2", 0.0),
        ("PC2_1", 0.0),
        ("CD1_2", 0.0),
        ("CD2_1", 0.0),
        ("PV2_1", 0.0),
        ("PV2_2", 0.0),
        ("LONPOLE", 180.0),
    ] {
        if let Some(v) = h.f64(key)?.filter(|v| *v != default) {
            return Err(invalid(
                path,
                format!("{key} = {v}: rotated or generalised projections are not supported (expected {default} or absent)"),
            ));
        }
    }

    let wcs_need = "the celestial coordinate system";
    let ra_deg = h.require_f64("CRVAL1", wcs_need)?;
    let dec_deg = h.require_f64("CRVAL2", wcs_need)?;
    if !(-90.0..=90.0).contains(&dec_deg) {
        return Err(invalid(
            path,
            format!("CRVAL2 = {dec_deg}: a declination must be within [-90, 90]"),
        ));
    }
    for (key, n) in [("CRPIX1", nx), ("CRPIX2", ny)] {
        let crpix = h.require_f64(key, wcs_need)?;
        let centre = (n / 2 + 1) as f64;
        if (crpix - centre).abs() > 1e-6 {
            return Err(invalid(
                path,
                format!("{key} = {crpix}: the reference pixel must be the image centre, {centre} for an axis of {n} pixels"),
            ));
        }
    }

    // Pixel increments: CD matrix (diagonal, checked above) or CDELT scaled by PC.
    let (k1, k2, d1, d2) = if let (Some(d1), Some(d2)) = (h.f64("CD1_1")?, h.f64("CD2_2")?) {
        ("CD1_1", "CD2_2", d1, d2)
    } else {
        let d1 = h.require_f64("CDELT1", wcs_need)? * h.f64("PC1_1")?.unwrap_or(1.0);
        let d2 = h.require_f64("CDELT2", wcs_need)? * h.f64("PC2_2")?.unwrap_or(1.0);
        ("CDELT1", "CDELT2", d1, d2)
    };
    if d1 == 0.0 || d2 == 0.0 {
        return Err(invalid(path, format!("{k1} = {d1}, {k2} = {d2}: pixel sizes must not be zero")));
    }
    if (d1.abs() - d2.abs()).abs() > 1e-9 * d2.abs() {
        return Err(invalid(
            path,
            format!("{k1} = {d1}, {k2} = {d2}: non-square pixels are not supported (expected {k1} = -{k2})"),
        ));
    }
    if !(d1 < 0.0 && d2 > 0.0) {
        return Err(invalid(
            path,
            format!(
                "{k1} = {d1}, {k2} = {d2}: flipped axes are not supported \
                 (expected RA increasing to the left, {k1} < 0, and Dec upwards, {k2} > 0)"
            ),
        ));
    }

    let (freq_hz, bandwidth_hz) = read_frequency(h, naxis)?;
    Ok(Some(ImageWcs { ra_deg, dec_deg, pixel_deg: d2, freq_hz, bandwidth_hz }))
}

/// CDELT of a FREQ axis whose bandwidth is not known: the FITS default, read back as unknown
/// (a real bandwidth of 1 Hz does not occur).
const UNKNOWN_BANDWIDTH: f64 = 1.0;

/// Frequency of the single plane and the bandwidth it covers, from a FREQ axis if any.
fn read_frequency(h: &mut HeaderReader, naxis: usize) -> Result<(Option<f64>, Option<f64>)> {
    for k in 3..=naxis {
        let is_freq =
            h.string(&format!("CTYPE{k}"))?.is_some_and(|t| t.to_ascii_uppercase().starts_with("FREQ"));
        if !is_freq {
            continue;
        }
        let crval = h.require_f64(&format!("CRVAL{k}"), "the FREQ axis")?;
        let crpix = h.f64(&format!("CRPIX{k}"))?.unwrap_or(1.0);
        let cdelt = h.f64(&format!("CDELT{k}"))?;
        if let Some(unit) = h.string(&format!("CUNIT{k}"))?.filter(|u| !u.eq_ignore_ascii_case("Hz")) {
            return Err(invalid(h.path, format!("CUNIT{k} = '{unit}': expected 'Hz' on the FREQ axis")));
        }
        // The plane is pixel 1 of the axis, wherever the reference pixel is.
        let freq = crval + (1.0 - crpix) * cdelt.unwrap_or(1.0);
        if freq <= 0.0 {
            return Err(invalid(
                h.path,
                format!("FREQ axis {k}: frequency {freq} Hz of the image plane is not positive"),
            ));
        }
        if cdelt == Some(0.0) {
            return Err(invalid(h.path, format!("CDELT{k} = 0: expected a non-zero bandwidth")));
        }
        return Ok((Some(freq), cdelt.filter(|&c| c != UNKNOWN_BANDWIDTH).map(f64::abs)));
    }
    Ok((None, None))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What a header card holds of a text, and the note that says what changed: every text
    /// made of it is one the keyword check accepts (so the write cannot fail on it).
    #[test]
    fn header_text_is_what_one_card_holds_and_says_what_it_changed() {
        assert_eq!(header_text("VLA"), ("VLA".to_string(), None));
        let (text, note) = header_text("ÅSKAP–Ø");
        assert_eq!(text, "?SKAP??");
        assert!(note.unwrap().contains("3 character(s) other than printable ASCII written as '?'"));
        let (text, note) = header_text(&"T".repeat(80));
        assert_eq!((text.len(), note.unwrap().contains("cut to 68 characters")), (68, true));
        // Quotes are doubled on the card: 40 of them fill 80 places, 34 fit.
        let (text, _) = header_text(&"'".repeat(40));
        assert_eq!(text.len(), 34);
        for value in ["ÅSKAP–Ø", &"T".repeat(80), &"'".repeat(40), "a\tb\n"] {
            let text = header_text(value).0;
            assert!(ExtraKeyword::parse("TELESCOP", &text).is_ok(), "{value:?} as {text:?}");
        }
    }

    #[test]
    fn output_prefixes_the_shell_did_not_expand_are_refused() {
        for prefix in ["~/x", "~", "$HOME/x", "out/${USER}/obs", "$TMPDIR"] {
            let e = check_output_prefix(prefix).unwrap_err();
            assert!(e.contains("no shell expanded"), "{prefix}: {e}");
        }
        for prefix in ["out/obs", "a$b/obs", "out/$5", "/data/obs", "x~/obs"] {
            assert!(check_output_prefix(prefix).is_ok(), "{prefix}");
        }
    }

    #[test]
    fn output_names_too_long_for_the_file_system_or_cfitsio_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let most = NAME_MAX - TEMP_NAME_EXTRA - LONGEST_PRODUCT_SUFFIX.len();
        let at = |stem: usize| format!("{}/{}", dir.path().display(), "x".repeat(stem));
        assert!(check_output_prefix(&at(most)).is_ok());
        let e = check_output_prefix(&at(most + 1)).unwrap_err();
        assert!(e.contains("prefix \"") && e.contains(&format!("{} bytes", most + 1 + LONGEST_PRODUCT_SUFFIX.len())) && e.contains("255"), "{e}");
        // The longest name allowed is written.
        let longest = PathBuf::from(format!("{}{LONGEST_PRODUCT_SUFFIX}", at(most)));
        write_image(&longest, &pattern(8, 8), 8, 8, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[]).unwrap();

        // Paths: cfitsio's limit, with the staging directory a prefix's products go through.
        let deep = |parts: usize, stem: usize| format!("{}/{}/{}", dir.path().display(), vec!["d".repeat(100); parts].join("/"), "p".repeat(stem));
        let e = check_output_prefix(&deep(10, 10)).unwrap_err();
        assert!(e.contains("cfitsio") && e.contains("1024") && e.contains("staging"), "{e}");
        assert!(check_output_prefix(&deep(5, 10)).is_ok());
        // A direct FITS file at cfitsio's limit is written; one byte more is refused.
        let base = dir.path().as_os_str().len() + 8 * 101 + 3 + TEMP_NAME_EXTRA;
        let stem = CFITSIO_PATH_MAX - base - ".fits".len();
        let file = PathBuf::from(format!("{}.fits", deep(8, stem)));
        check_output_file(&file, true).unwrap();
        std::fs::create_dir_all(file.parent().unwrap()).unwrap();
        write_image(&file, &pattern(8, 8), 8, 8, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[]).unwrap();
        let e = check_output_file(&PathBuf::from(format!("{}.fits", deep(8, stem + 1))), true).unwrap_err();
        assert!(e.contains("cfitsio") && e.contains("1024"), "{e}");
        assert!(check_output_file(&PathBuf::from(format!("{}.parquet", deep(8, stem + 1))), false).is_ok());
    }

    #[test]
    fn output_files_that_name_directories_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        for path in ["o/", "o/.", "..", "."] {
            let e = check_output_file(Path::new(path), false).unwrap_err();
            assert!(e.contains(&format!("\"{path}\" names a directory")), "{e}");
        }
        let e = check_output_file(dir.path(), false).unwrap_err();
        assert!(e.contains("is a directory") && e.contains("obs.parquet"), "{e}");
        assert!(check_output_file(&dir.path().join("obs.parquet"), false).is_ok());
    }

    fn test_wcs() -> ImageWcs {
        ImageWcs {
            ra_deg: 187.5,
            dec_deg: 41.25,
            pixel_deg: 1.0 / 3600.0,
            freq_hz: Some(1.4e9),
            bandwidth_hz: Some(8.0e6),
        }
    }

    /// A non-symmetric test pattern, so that transpositions and flips show.
    fn pattern(nx: usize, ny: usize) -> Vec<f64> {
        (0..nx * ny)
            .map(|i| {
                let (ix, iy) = ((i % nx) as f64, (i / nx) as f64);
                0.1 * ix - 0.003 * iy * iy + (0.37 * ix * iy).sin() * 1e-4
            })
            .collect()
    }

    /// Header floats carry 15 significant digits (cfitsio's default, as in WSClean's files).
    fn assert_wcs_close(a: &ImageWcs, b: &ImageWcs) {
        let close = |x: f64, y: f64| (x - y).abs() <= 1e-14 * y.abs().max(1.0);
        assert!(close(a.ra_deg, b.ra_deg) && close(a.dec_deg, b.dec_deg), "{a:?} vs {b:?}");
        assert!((a.pixel_deg / b.pixel_deg - 1.0).abs() < 1e-14, "{a:?} vs {b:?}");
    }

    /// Creates a float32 image with fitsio directly; `shape` is slowest axis first.
    fn write_raw(path: &Path, shape: &[usize], data: &[f32], keys: &[(&str, f64)]) {
        let description = ImageDescription { data_type: ImageType::Float, dimensions: shape };
        let mut f = FitsFile::create(path).with_custom_primary(&description).open().unwrap();
        let hdu = f.primary_hdu().unwrap();
        for (k, v) in keys {
            hdu.write_key(&mut f, k, *v).unwrap();
        }
        hdu.write_image(&mut f, data).unwrap();
    }

    fn dir_entries(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn round_trip_preserves_pixels_wcs_and_keywords() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("image.fits");
        let (nx, ny) = (64, 48);
        let image = pattern(nx, ny);
        let beam = Beam { major_deg: 2e-3, minor_deg: 1e-3, pa_deg: 30.0 };
        let extra =
            [("NITER", "500".to_string()), ("GAIN", "0.1".to_string()), ("OBJECT", "3C 286".to_string())];
        write_image(&path, &image, nx, ny, &test_wcs(), BrightnessUnit::JyPerBeam, Some(&beam), &extra)
            .unwrap();

        let read = read_image(&path).unwrap();
        assert_eq!((read.nx, read.ny), (nx, ny));
        for (a, b) in image.iter().zip(&read.data) {
            assert_eq!(*b, *a as f32 as f64);
        }
        let wcs = read.wcs.unwrap();
        let expected = test_wcs();
        assert_wcs_close(&wcs, &expected);
        assert_eq!(wcs.freq_hz, expected.freq_hz);
        assert_eq!(wcs.bandwidth_hz, expected.bandwidth_hz);
        assert_eq!(read.unit.as_deref(), Some("JY/BEAM"));

        let mut f = FitsFile::open(&path).unwrap();
        let hdu = f.primary_hdu().unwrap();
        assert_eq!(hdu.read_key::<i64>(&mut f, "NAXIS").unwrap(), 4);
        assert_eq!(hdu.read_key::<i64>(&mut f, "BITPIX").unwrap(), -32);
        assert_eq!(hdu.read_key::<String>(&mut f, "CTYPE4").unwrap(), "STOKES");
        assert_eq!(hdu.read_key::<i64>(&mut f, "NITER").unwrap(), 500);
        assert_eq!(hdu.read_key::<f64>(&mut f, "GAIN").unwrap(), 0.1);
        assert_eq!(hdu.read_key::<String>(&mut f, "OBJECT").unwrap(), "3C 286");
        assert_eq!(hdu.read_key::<f64>(&mut f, "BMAJ").unwrap(), 2e-3);
        assert_eq!(hdu.read_key::<String>(&mut f, "RADESYS").unwrap(), "FK5");
    }

    #[test]
    fn the_primary_hdu_carries_no_extname() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("image.fits");
        write_image(&path, &pattern(8, 8), 8, 8, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[]).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        // The header: 80-character cards up to END.
        let cards: Vec<&[u8]> = bytes.chunks(80).take_while(|c| !c.starts_with(b"END ")).collect();
        assert!(cards.iter().any(|c| c.starts_with(b"BUNIT ")), "the header was not read");
        assert!(!cards.iter().any(|c| c.starts_with(b"EXTNAME")), "EXTNAME in the primary header");
        // The file still reads, with its WCS.
        assert_wcs_close(&read_image(&path).unwrap().wcs.unwrap(), &test_wcs());
    }

    #[test]
    fn unknown_frequency_gives_three_axes_with_stokes_third() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.fits");
        let wcs = ImageWcs { freq_hz: None, bandwidth_hz: None, ..test_wcs() };
        write_image(&path, &pattern(8, 8), 8, 8, &wcs, BrightnessUnit::JyPerPixel, None, &[]).unwrap();

        let mut f = FitsFile::open(&path).unwrap();
        let hdu = f.primary_hdu().unwrap();
        assert_eq!(hdu.read_key::<i64>(&mut f, "NAXIS").unwrap(), 3);
        assert_eq!(hdu.read_key::<String>(&mut f, "CTYPE3").unwrap(), "STOKES");
        let read = read_image(&path).unwrap();
        let read_wcs = read.wcs.unwrap();
        assert_wcs_close(&read_wcs, &wcs);
        assert_eq!((read_wcs.freq_hz, read_wcs.bandwidth_hz), (None, None));
        assert_eq!(read.unit.as_deref(), Some("JY/PIXEL"));
    }

    #[test]
    fn writing_leaves_no_temporary_and_overwrites() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.fits");
        std::fs::write(&path, b"old contents").unwrap();
        write_image(&path, &pattern(16, 16), 16, 16, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[])
            .unwrap();
        assert_eq!(dir_entries(dir.path()), vec!["out.fits"]);
        assert_eq!(read_image(&path).unwrap().nx, 16);

        // A failure at the very end (the target is a directory) still cleans up.
        let blocked = dir.path().join("blocked.fits");
        std::fs::create_dir(&blocked).unwrap();
        let err =
            write_image(&blocked, &pattern(4, 4), 4, 4, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[])
                .unwrap_err();
        assert!(err.to_string().contains("blocked.fits"), "{err}");
        assert_eq!(dir_entries(dir.path()), vec!["blocked.fits", "out.fits"]);
    }

    #[test]
    fn reading_a_missing_file_names_the_path() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("no-such-image.fits");
        let err = read_image(&path).unwrap_err();
        assert!(err.to_string().contains("no-such-image.fits"), "{err}");
    }

    #[test]
    fn a_file_that_is_not_fits_is_a_cfitsio_error_keeping_its_status() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("notes.fits");
        std::fs::write(&path, "these are notes, not an image\n".repeat(200)).unwrap();
        let err = read_image(&path).unwrap_err();
        let Error::Fits(FitsError::Cfitsio { path: named, doing, source }) = &err else { panic!("not a cfitsio error: {err:?}") };
        assert_eq!((named.as_path(), doing.as_str()), (path.as_path(), "cannot open as FITS"));
        let status = source.status().expect("cfitsio's own status");
        assert!(status > 0, "{status}");
        // Error -> FitsError -> Cfitsio, the last holding fitsio's error.
        let module = std::error::Error::source(&err).expect("the FITS error");
        assert!(module.downcast_ref::<FitsError>().is_some());
        let cause = module.source().and_then(|c| c.downcast_ref::<Cfitsio>()).expect("cfitsio's error");
        assert!(matches!(cause.0, FitsioError::Fits(ref e) if e.status == status));
        // The message says the file, what failed and cfitsio's words, each once.
        let text = err.to_string();
        let cfitsio_text = cause.to_string();
        assert!(cfitsio_text.contains(&format!("cfitsio status {status}")), "{cfitsio_text}");
        assert_eq!(text, format!("{}: cannot open as FITS: {cfitsio_text}", path.display()));
        assert_eq!(crate::error::Report(&err).to_string(), text);
    }

    #[test]
    fn a_failed_write_keeps_the_system_reason_and_cfitsio_report() {
        let dir = tempfile::tempdir().unwrap();
        // The directory the file would go in does not exist: cfitsio cannot create it, and the
        // probe of the directory finds why.
        let path = dir.path().join("missing-dir").join("out.fits");
        let err = write_image(&path, &pattern(4, 4), 4, 4, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[]).unwrap_err();
        let Error::Io { path: named, source } = &err else { panic!("not an I/O error: {err:?}") };
        assert_eq!(named, &path);
        assert_eq!(source.kind(), std::io::ErrorKind::NotFound, "{source:?}");
        let failure = source.get_ref().and_then(|e| e.downcast_ref::<WriteFailure>()).expect("cfitsio's report inside");
        assert!(failure.cfitsio.status().is_some() && failure.disk.is_some(), "{failure:?}");
        let text = err.to_string();
        let os = failure.disk.as_ref().unwrap().to_string();
        assert_eq!(text.matches(&os).count(), 1, "{text}");
        assert!(text.contains("writing FITS image") && text.contains("cfitsio status"), "{text}");
    }

    #[test]
    fn cube_with_two_planes_is_rejected_naming_naxis3() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cube.fits");
        write_raw(&path, &[2, 4, 4], &[0.0; 32], &[]);
        let err = read_image(&path).unwrap_err();
        assert!(err.to_string().contains("NAXIS3 = 2"), "{err}");
        assert!(matches!(err, Error::Fits(FitsError::Invalid { .. })), "{err:?}");
    }

    #[test]
    fn non_finite_pixels_are_rejected_with_count() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("nan.fits");
        let mut data = vec![1.0f32; 16];
        data[3] = f32::NAN;
        data[7] = f32::INFINITY;
        write_raw(&path, &[4, 4], &data, &[]);
        let err = read_image(&path).unwrap_err().to_string();
        assert!(err.contains("nan.fits") && err.contains("2 of 16"), "{err}");

        let err = write_image(&path, &[f64::NAN; 4], 2, 2, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[])
            .unwrap_err();
        assert!(err.to_string().contains("4 of 4"), "{err}");
        // Blanks where they are meant (a primary-beam corrected image): NaN written, infinity not.
        let blanked = [f64::NAN, 1.0, 2.0, f64::NAN];
        write_image(&path, Pixels::blanked(&blanked), 2, 2, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[]).unwrap();
        let mut f = FitsFile::open(&path).unwrap();
        let back: Vec<f32> = f.primary_hdu().unwrap().read_image(&mut f).unwrap();
        assert!(back[0].is_nan() && back[3].is_nan() && back[1..3] == [1.0, 2.0], "{back:?}");
        let err = write_image(&path, Pixels::blanked(&[f64::INFINITY, 0.0]), 2, 1, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[]).unwrap_err();
        assert!(err.to_string().contains("1 of 2"), "{err}");
    }

    #[test]
    fn integer_image_is_scaled_and_wcs_less_image_has_none() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("int.fits");
        {
            let description = ImageDescription { data_type: ImageType::Short, dimensions: &[2, 3] };
            let mut f = FitsFile::create(&path).with_custom_primary(&description).open().unwrap();
            let hdu = f.primary_hdu().unwrap();
            hdu.write_key(&mut f, "BSCALE", 0.5f64).unwrap();
            hdu.write_key(&mut f, "BZERO", 10.0f64).unwrap();
            hdu.write_image(&mut f, &[0i16, 1, 2, 3, 4, 5]).unwrap();
        }
        let read = read_image(&path).unwrap();
        assert_eq!((read.nx, read.ny), (3, 2));
        assert_eq!(read.data, vec![10.0, 10.5, 11.0, 11.5, 12.0, 12.5]);
        assert_eq!(read.wcs, None);
        assert_eq!(read.unit, None);
    }

    /// Scaled integers (BITPIX 8 and 16 with a BSCALE that makes them float) are as many bytes
    /// per pixel in the file as BITPIX says, not as the float they scale to.
    #[test]
    fn scaled_integer_images_are_read_at_their_stored_size() {
        let dir = tempfile::tempdir().unwrap();
        let (nx, ny) = (64, 64);
        let codes: Vec<i64> = (0..nx * ny).map(|k| (k % 200) as i64).collect();
        for (name, image_type) in [("b8.fits", ImageType::UnsignedByte), ("s16.fits", ImageType::Short)] {
            let path = dir.path().join(name);
            {
                let description = ImageDescription { data_type: image_type, dimensions: &[ny, nx] };
                let mut f = FitsFile::create(&path).with_custom_primary(&description).open().unwrap();
                let hdu = f.primary_hdu().unwrap();
                hdu.write_key(&mut f, "BSCALE", 0.01f64).unwrap();
                hdu.write_key(&mut f, "BZERO", -1.0f64).unwrap();
                // Stored as they are: cfitsio takes up scaling keywords when it next opens the
                // HDU (as `integer_image_is_scaled_and_wcs_less_image_has_none` relies on).
                let stored: Vec<i16> = codes.iter().map(|&c| c as i16).collect();
                hdu.write_image(&mut f, &stored).unwrap();
            }
            let read = read_image(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!((read.nx, read.ny), (nx, ny));
            for (k, (&value, &code)) in read.data.iter().zip(&codes).enumerate() {
                assert!((value - (code as f64 * 0.01 - 1.0)).abs() < 1e-9, "{name}: pixel {k}: {value} for code {code}");
            }
        }
    }

    /// A gzip-compressed image reads as its decompressed file; one decompressing to more
    /// than the budget is refused as it passes it, and damaged compression is named.
    #[test]
    fn gzip_compressed_images_are_read_within_the_budget() {
        use std::io::Write;
        let dir = tempfile::tempdir().unwrap();
        let plain = dir.path().join("plain.fits");
        write_image(&plain, &pattern(64, 64), 64, 64, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[]).unwrap();
        let bytes = std::fs::read(&plain).unwrap();
        let gz = dir.path().join("sky.fits.gz");
        let mut encoder = flate2::write::GzEncoder::new(std::fs::File::create(&gz).unwrap(), flate2::Compression::default());
        encoder.write_all(&bytes).unwrap();
        encoder.finish().unwrap();
        let (a, b) = (read_image(&gz).unwrap(), read_image(&plain).unwrap());
        assert_eq!((a.data, a.wcs, a.unit), (b.data, b.wcs, b.unit));
        let small = crate::limits::MemoryBudget { bytes: bytes.len() as u64 - 1, origin: "the test" };
        let e = read_image_within(&gz, small).unwrap_err().to_string();
        assert!(e.contains("sky.fits.gz") && e.contains("decompresses to more than") && e.contains("the test"), "{e}");
        let gz_bytes = std::fs::read(&gz).unwrap();
        std::fs::write(&gz, &gz_bytes[..gz_bytes.len() / 2]).unwrap();
        let e = read_image(&gz).unwrap_err().to_string();
        assert!(e.contains("sky.fits.gz") && e.contains("does not decompress"), "{e}");
    }

    #[test]
    fn truncated_file_is_rejected_before_reading() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("short.fits");
        write_image(&path, &pattern(64, 64), 64, 64, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[])
            .unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        let err = read_image(&path).unwrap_err().to_string();
        assert!(err.contains("short.fits") && err.contains("64 x 64"), "{err}");
    }

    #[test]
    fn non_square_pixels_are_rejected() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rect.fits");
        write_image(&path, &pattern(8, 8), 8, 8, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[]).unwrap();
        {
            let mut f = FitsFile::edit(&path).unwrap();
            let hdu = f.primary_hdu().unwrap();
            hdu.write_key(&mut f, "CDELT1", -2.0 / 3600.0).unwrap();
        }
        let err = read_image(&path).unwrap_err().to_string();
        assert!(err.contains("non-square pixels") && err.contains("CDELT1"), "{err}");
    }

    #[test]
    fn bad_extra_keywords_and_parameters_are_rejected() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.fits");
        let write = |extra: &[(&str, String)]| {
            write_image(&path, &pattern(4, 4), 4, 4, &test_wcs(), BrightnessUnit::JyPerBeam, None, extra)
        };
        let err = write(&[("CRVAL1", "3".to_string())]).unwrap_err().to_string();
        assert!(err.contains("CRVAL1"), "{err}");
        let err = write(&[("TOOLONGNAME", "3".to_string())]).unwrap_err().to_string();
        assert!(err.contains("TOOLONGNAME"), "{err}");
        let err = write(&[("NOTE", "x".repeat(80))]).unwrap_err().to_string();
        assert!(err.contains("NOTE"), "{err}");
        let err = write_image(&path, &pattern(4, 4), 4, 5, &test_wcs(), BrightnessUnit::JyPerBeam, None, &[])
            .unwrap_err()
            .to_string();
        assert!(err.contains("16 pixels"), "{err}");
        assert!(dir_entries(dir.path()).is_empty());
    }

    /// Pixel-to-world by FITS WCS paper II (Calabretta & Greisen 2002), from the header
    /// keywords alone: intermediate coordinates x = CDELT1 (p1 - CRPIX1), y = CDELT2
    /// (p2 - CRPIX2); SIN deprojection phi = arg(-y, x), theta = acos(R); rotation from
    /// native to celestial with (alpha0, delta0) = CRVAL and phi_p = LONPOLE = 180 deg.
    fn sin_pixel_to_world(keys: &[f64; 6], ix: usize, iy: usize) -> (f64, f64) {
        let [crpix1, crpix2, crval1, crval2, cdelt1, cdelt2] = *keys;
        let x = (cdelt1 * (ix as f64 + 1.0 - crpix1)).to_radians();
        let y = (cdelt2 * (iy as f64 + 1.0 - crpix2)).to_radians();
        let r = x.hypot(y);
        let phi = x.atan2(-y);
        let theta = r.acos();
        let (dp, phi_p) = (crval2.to_radians(), std::f64::consts::PI);
        let alpha = crval1.to_radians()
            + (-theta.cos() * (phi - phi_p).sin())
                .atan2(theta.sin() * dp.cos() - theta.cos() * dp.sin() * (phi - phi_p).cos());
        let delta = (theta.sin() * dp.sin() + theta.cos() * dp.cos() * (phi - phi_p).cos()).asin();
        (alpha.to_degrees().rem_euclid(360.0), delta.to_degrees())
    }

    /// The imager's convention: direction cosines l = -pixel (ix - nx/2) towards
    /// increasing RA, m = pixel (iy - ny/2), with the standard (l, m) to (RA, Dec).
    fn direction_cosines_to_world(wcs: &ImageWcs, nx: usize, ny: usize, ix: usize, iy: usize) -> (f64, f64) {
        let pixel = wcs.pixel_deg.to_radians();
        let l = -pixel * (ix as f64 - (nx / 2) as f64);
        let m = pixel * (iy as f64 - (ny / 2) as f64);
        let n = (1.0 - l * l - m * m).sqrt();
        let (ra0, dec0) = (wcs.ra_deg.to_radians(), wcs.dec_deg.to_radians());
        let ra = ra0 + l.atan2(dec0.cos() * n - m * dec0.sin());
        let dec = (m * dec0.cos() + dec0.sin() * n).asin();
        (ra.to_degrees().rem_euclid(360.0), dec.to_degrees())
    }

    fn angle_diff(a: f64, b: f64) -> f64 {
        (a - b + 180.0).rem_euclid(360.0) - 180.0
    }

    #[test]
    fn wcs_pixels_map_to_sky_like_the_imager() {
        let dir = tempfile::tempdir().unwrap();
        let (nx, ny) = (128, 96);
        for (k, (ra, dec)) in [(187.5, 41.25), (359.99, -43.02), (0.005, 2.0)].into_iter().enumerate() {
            let wcs = ImageWcs { ra_deg: ra, dec_deg: dec, pixel_deg: 2.0 / 3600.0, ..test_wcs() };
            let path = dir.path().join(format!("wcs{k}.fits"));
            write_image(&path, &pattern(nx, ny), nx, ny, &wcs, BrightnessUnit::JyPerBeam, None, &[]).unwrap();
            if let Some(out) = std::env::var_os("R2D2_WCS_FITS_OUT").filter(|_| k == 0) {
                // For tests/wcs_astropy.py: a file to check against astropy.
                std::fs::copy(&path, out).unwrap();
            }

            let mut f = FitsFile::open(&path).unwrap();
            let hdu = f.primary_hdu().unwrap();
            let mut keys = [0.0; 6];
            for (v, name) in keys.iter_mut().zip(["CRPIX1", "CRPIX2", "CRVAL1", "CRVAL2", "CDELT1", "CDELT2"])
            {
                *v = hdu.read_key::<f64>(&mut f, name).unwrap();
            }

            let (ra_c, dec_c) = sin_pixel_to_world(&keys, nx / 2, ny / 2);
            assert!(
                angle_diff(ra_c, ra).abs() < 1e-12 && (dec_c - dec).abs() < 1e-12,
                "centre at {ra_c}, {dec_c}"
            );

            let (ra1, dec1) = sin_pixel_to_world(&keys, nx / 2 - 10, ny / 2 + 5);
            assert!(angle_diff(ra1, ra) > 0.0, "east must be left: {ra1} vs {ra}");
            assert!(dec1 > dec);

            for (ix, iy) in [(nx / 2 - 10, ny / 2 + 5), (0, 0), (nx - 1, ny - 1), (3, ny - 2), (nx - 7, 1)] {
                let (ra_w, dec_w) = sin_pixel_to_world(&keys, ix, iy);
                let (ra_d, dec_d) = direction_cosines_to_world(&wcs, nx, ny, ix, iy);
                assert!(angle_diff(ra_w, ra_d).abs() < 1e-9, "pixel ({ix}, {iy}): RA {ra_w} vs {ra_d}");
                assert!((dec_w - dec_d).abs() < 1e-9, "pixel ({ix}, {iy}): Dec {dec_w} vs {dec_d}");
            }
        }
    }
}
