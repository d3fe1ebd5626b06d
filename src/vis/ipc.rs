//! Arrow IPC tables (a stream or a file, standard input included) read batch by batch, with
//! the message framing done here so that no declared size is trusted.
//!
//! Arrow IPC carries the same columns as the Parquet format, and the observation metadata
//! (`phase_centre_ra_deg`, ...) as schema metadata, which is where
//! `pyarrow.ipc.new_stream(sink, schema.with_metadata({...}))` puts it.

use super::reader::{TableReader, STDIN};
use super::{contain_panics, validate_schema, ObservationMeta, ARROW_IPC};
use crate::{Error, Result};
use arrow::array::RecordBatch;
use arrow::datatypes::{Schema, SchemaRef};
use arrow::ipc::reader::{read_dictionary, read_record_batch};
use arrow::ipc::MessageHeader;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// An Arrow IPC table: the stream format (from a file or standard input) or the file format
/// (from a file), told apart by the file format's leading magic bytes.
///
/// Messages are framed here rather than by arrow's `StreamReader`, which allocates whatever a
/// header declares (a 1 TiB body aborted the process): every declared size is checked first
/// against what the input can still hold (a file's remaining bytes) and the memory available,
/// and buffers grow with the bytes that actually arrive. The file format is read through the
/// stream it embeds (its messages in order, up to the end-of-stream marker before the footer),
/// so the footer's block sizes, which are as untrusted, are never used.
pub struct IpcReader {
    source: PathBuf,
    meta: ObservationMeta,
    schema: SchemaRef,
    messages: IpcMessages,
    rows: u64,
    finished: bool,
    /// Accept a stream that ends without its end-of-stream marker (with a warning).
    allow_truncated: bool,
}

/// The IPC file format starts with these bytes; the stream format with a message length.
const IPC_FILE_MAGIC: &[u8] = b"ARROW1";

impl IpcReader {
    /// Opens `input` (a path, or `-` for standard input) and reads the schema and metadata.
    /// With `allow_truncated`, a stream that ends between two messages without its end-of-stream
    /// marker is taken as complete (with a warning) instead of an error.
    pub fn open(input: &str, allow_truncated: bool) -> Result<IpcReader> {
        if input == STDIN {
            let source = PathBuf::from("standard input");
            let mut reader = BufReader::new(std::io::stdin());
            if peek_is_file_format(&mut reader, &source)? {
                return Err(Error::input(
                    &source,
                    "this is the Arrow IPC file format, which needs a seekable file: send the stream format on standard input, or give the file's path",
                ));
            }
            return Self::new(source, IpcMessages::new(Box::new(reader), None, false), allow_truncated);
        }
        let source = PathBuf::from(input);
        let file = std::fs::File::open(&source).map_err(|e| Error::io(&source, e))?;
        let metadata = file.metadata().map_err(|e| Error::io(&source, e))?;
        // A pipe's length is 0 whatever it will carry: only a regular file's bounds the messages.
        let length = metadata.is_file().then(|| metadata.len());
        let mut reader = BufReader::new(file);
        let file_format = peek_is_file_format(&mut reader, &source)?;
        let header = if file_format { skip_file_header(&mut reader, &source)? } else { 0 };
        let mut messages = IpcMessages::new(Box::new(reader), length.map(|length| length.saturating_sub(header)), file_format);
        messages.offset = header;
        Self::new(source, messages, allow_truncated)
    }

    fn new(source: PathBuf, mut messages: IpcMessages, allow_truncated: bool) -> Result<IpcReader> {
        let first = contain_panics(&source, "not a readable Arrow IPC stream", ARROW_IPC, || messages.next(None))?;
        let IpcMessage::Schema(schema) = first else {
            return Err(Error::input(&source, "not a readable Arrow IPC stream: it does not start with a schema"));
        };
        let schema = Arc::new(schema);
        let name = source.display().to_string();
        let meta = ObservationMeta::from_pairs(schema.metadata().iter().map(|(k, v)| (k.as_str(), Some(v.as_str()))), &name)?;
        validate_schema(&schema, &name)?;
        Ok(IpcReader { source, meta, schema, messages, rows: 0, finished: false, allow_truncated })
    }
}

/// Whether the buffered input starts with the IPC file magic (without consuming it).
fn peek_is_file_format<R: Read>(reader: &mut BufReader<R>, source: &Path) -> Result<bool> {
    let head = reader.fill_buf().map_err(|e| Error::io(source, e))?;
    if head.is_empty() {
        return Err(Error::input(source, "empty input: expected an Arrow IPC stream or file"));
    }
    Ok(head.starts_with(IPC_FILE_MAGIC))
}

/// Skips the file format's magic and the padding after it (to 8 bytes, or to 64 as arrow-rs
/// writes it), up to its first message; the bytes skipped.
fn skip_file_header(reader: &mut BufReader<std::fs::File>, source: &Path) -> Result<u64> {
    let mut magic = [0u8; 8];
    reader.read_exact(&mut magic).map_err(|_| Error::input(source, "too short for the Arrow IPC file format"))?;
    let mut skipped = magic.len();
    // Zero words before the schema can only be padding: a stream does not start by ending.
    while skipped < 64 && reader.fill_buf().map_err(|e| Error::io(source, e))?.starts_with(&[0; 4]) {
        reader.consume(4);
        skipped += 4;
    }
    Ok(skipped as u64)
}

impl TableReader for IpcReader {
    fn source(&self) -> &Path {
        &self.source
    }
    fn meta(&self) -> &ObservationMeta {
        &self.meta
    }
    fn schema(&self) -> SchemaRef {
        self.schema.clone()
    }
    fn next_batch(&mut self) -> Option<Result<RecordBatch>> {
        while !self.finished {
            let what = format!("corrupt Arrow IPC data after row {}", self.rows);
            let (messages, schema) = (&mut self.messages, &self.schema);
            match contain_panics(&self.source, &what, ARROW_IPC, || messages.next(Some(schema))) {
                Ok(IpcMessage::Batch(batch)) => {
                    self.rows += batch.num_rows() as u64;
                    return Some(Ok(batch));
                }
                Ok(IpcMessage::Other) => continue,
                Ok(IpcMessage::Schema(_)) => {
                    self.finished = true;
                    return Some(Err(Error::input(&self.source, format!("{what}: a second schema in the stream"))));
                }
                Ok(IpcMessage::End) => {
                    self.finished = true;
                    // The file format's footer follows its marker; in a stream, more bytes are
                    // another stream (files concatenated), which would otherwise be dropped.
                    // Standard input is not read past the marker: its sender may hold it open.
                    let (offset, left) = (self.messages.offset, self.messages.left.unwrap_or(0));
                    if !self.messages.file_format && left > 0 {
                        return Some(Err(Error::input(
                            &self.source,
                            format!(
                                "{left} more bytes follow the Arrow IPC end-of-stream marker, from byte offset {offset} (after row {}): a second stream appended to the first? Write one stream, or convert each separately",
                                self.rows
                            ),
                        )));
                    }
                }
                Ok(IpcMessage::EndOfInput) => {
                    // A sender that died between two batches leaves a stream that looks whole
                    // but for the marker: imaging it silently would pass part of an
                    // observation off as all of it.
                    self.finished = true;
                    let ended = format!("the Arrow IPC stream ended after row {} without its end-of-stream marker", self.rows);
                    if !self.allow_truncated {
                        return Some(Err(Error::input(
                            &self.source,
                            format!("{ended}: the sender may have stopped part-way (if these rows are all there is, set allow_truncated: true on the source)"),
                        )));
                    }
                    log::warn!("{}: {ended}: imaging the rows received (allow_truncated)", self.source.display());
                }
                Err(e) => {
                    self.finished = true;
                    return Some(Err(e));
                }
            }
        }
        None
    }
}

/// One message of an IPC stream, decoded.
enum IpcMessage {
    Schema(Schema),
    Batch(RecordBatch),
    /// A dictionary (kept for the batches that follow) or an empty message.
    Other,
    /// The end-of-stream marker.
    End,
    /// The input ended between two messages, without the end-of-stream marker.
    EndOfInput,
}

/// Marks a message length that follows (IPC format 0.15 and later).
const CONTINUATION: [u8; 4] = [0xff; 4];

/// Largest message header (a flatbuffer: the schema and its metadata, or a batch's buffer
/// list) accepted. A visibility table's take a few kilobytes.
const MAX_HEADER_BYTES: u64 = 16 << 20;

/// Bodies are read in steps that double up to what the header declares, so that a lying
/// header costs at most twice the bytes that actually arrived.
const FIRST_READ_BYTES: usize = 1 << 20;

/// The messages of an Arrow IPC stream, framed and bounded (see [`IpcReader`]).
struct IpcMessages {
    input: Box<dyn Read>,
    /// Bytes left in the input, when it is a file.
    left: Option<u64>,
    /// Bytes of the input consumed (the file format's header included).
    offset: u64,
    /// The IPC file format: its footer follows the end-of-stream marker.
    file_format: bool,
    dictionaries: std::collections::HashMap<i64, arrow::array::ArrayRef>,
}

impl IpcMessages {
    fn new(input: Box<dyn Read>, left: Option<u64>, file_format: bool) -> IpcMessages {
        IpcMessages { input, left, offset: 0, file_format, dictionaries: Default::default() }
    }

    /// Reads until `buf` is full or the input ends; the number of bytes read.
    fn fill(&mut self, buf: &mut [u8]) -> std::result::Result<usize, String> {
        let mut got = 0;
        while got < buf.len() {
            match self.input.read(&mut buf[got..]) {
                Ok(0) => break,
                Ok(n) => got += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(format!("reading: {e}")),
            }
        }
        if let Some(left) = &mut self.left {
            *left = left.saturating_sub(got as u64);
        }
        self.offset += got as u64;
        Ok(got)
    }

    /// Refuses a declared size beyond what the input holds or `limit` allows.
    fn check_declared(&self, what: &str, declared: u64, limit: u64, limit_text: &dyn std::fmt::Display) -> std::result::Result<(), String> {
        if let Some(left) = self.left.filter(|&left| declared > left) {
            return Err(format!("a {what} of {declared} bytes is declared, but only {left} bytes are left in the input"));
        }
        if declared > limit {
            let size = crate::limits::format_bytes(declared as f64);
            return Err(format!("a {what} of {declared} bytes ({size}) is declared, more than {limit_text}"));
        }
        Ok(())
    }

    /// Reads `length` bytes (already checked) into an aligned buffer.
    fn read_block(&mut self, length: u64, what: &str) -> std::result::Result<arrow::buffer::Buffer, String> {
        let length = usize::try_from(length).map_err(|_| format!("a {what} of {length} bytes does not fit in memory"))?;
        let mut block = arrow::buffer::MutableBuffer::new(0);
        while block.len() < length {
            let start = block.len();
            let end = length.min(start + start.max(FIRST_READ_BYTES));
            block.resize(end, 0);
            if self.fill(&mut block.as_slice_mut()[start..end])? < end - start {
                return Err(format!("the input ends part-way through a {what} (truncated)"));
            }
        }
        Ok(block.into())
    }

    /// The next message; `schema` is the stream's, once read.
    fn next(&mut self, schema: Option<&SchemaRef>) -> std::result::Result<IpcMessage, String> {
        let mut word = [0u8; 4];
        match self.fill(&mut word)? {
            0 => return Ok(IpcMessage::EndOfInput),
            4 => {}
            _ => return Err("the input ends part-way through a message length (truncated)".into()),
        }
        if word == CONTINUATION && self.fill(&mut word)? < 4 {
            return Err("the input ends part-way through a message length (truncated)".into());
        }
        let length = i32::from_le_bytes(word);
        if length == 0 {
            return Ok(IpcMessage::End);
        }
        let length = u64::try_from(length).map_err(|_| format!("a negative message header length ({length})"))?;
        self.check_declared("message header", length, MAX_HEADER_BYTES, &"the largest header accepted (16 MiB)")?;
        let header = self.read_block(length, "message header")?;
        let message = arrow::ipc::root_as_message(&header).map_err(|e| format!("not an Arrow IPC message header: {e}"))?;
        let body_length = message.bodyLength();
        let body_length = u64::try_from(body_length).map_err(|_| format!("a negative message body length ({body_length})"))?;
        let budget = crate::limits::memory_budget();
        self.check_declared("message body", body_length, budget.bytes, &budget)?;
        let body = self.read_block(body_length, "message body")?;
        let version = message.version();
        let missing = |what: &str| format!("a {what} message without its header");
        match message.header_type() {
            MessageHeader::Schema => {
                let schema = message.header_as_schema().ok_or_else(|| missing("schema"))?;
                Ok(IpcMessage::Schema(arrow::ipc::convert::fb_to_schema(schema)))
            }
            MessageHeader::RecordBatch => {
                let schema = schema.ok_or("a record batch before the schema")?;
                let batch = message.header_as_record_batch().ok_or_else(|| missing("record batch"))?;
                check_decompressed_size(&body, batch, "record batch")?;
                read_record_batch(&body, batch, schema.clone(), &self.dictionaries, None, &version)
                    .map(IpcMessage::Batch)
                    .map_err(|e| e.to_string())
            }
            MessageHeader::DictionaryBatch => {
                let schema = schema.ok_or("a dictionary before the schema")?;
                let dictionary = message.header_as_dictionary_batch().ok_or_else(|| missing("dictionary"))?;
                if let Some(batch) = dictionary.data() {
                    check_decompressed_size(&body, batch, "dictionary")?;
                }
                read_dictionary(&body, dictionary, schema, &mut self.dictionaries, &version).map_err(|e| e.to_string())?;
                Ok(IpcMessage::Other)
            }
            MessageHeader::NONE => Ok(IpcMessage::Other),
            other => Err(format!("unexpected {other:?} message (a visibility table has a schema and record batches)")),
        }
    }
}

/// Refuses a compressed (LZ4 or ZSTD) batch whose buffers declare more bytes once decompressed
/// than the memory budget allows: arrow sizes each buffer's allocation by the length that its
/// first 8 bytes declare, before decompressing anything.
fn check_decompressed_size(body: &[u8], batch: arrow::ipc::RecordBatch<'_>, what: &str) -> std::result::Result<(), String> {
    if batch.compression().is_none() {
        return Ok(());
    }
    let mut declared = 0u64;
    for buffer in batch.buffers().into_iter().flatten() {
        if buffer.length() < 8 {
            continue; // empty: nothing is decompressed
        }
        let start = usize::try_from(buffer.offset()).ok();
        let prefix = start.and_then(|start| body.get(start..start.checked_add(8)?)).ok_or_else(|| {
            format!("a compressed buffer at offset {} of the {what}'s body lies past its end ({} bytes)", buffer.offset(), body.len())
        })?;
        // -1: stored uncompressed; 0: empty.
        let length = i64::from_le_bytes(prefix.try_into().expect("8 bytes"));
        declared = declared.saturating_add(u64::try_from(length).unwrap_or(0));
    }
    let budget = crate::limits::memory_budget();
    if declared > budget.bytes {
        let size = crate::limits::format_bytes(declared as f64);
        return Err(format!("a compressed {what} declares {declared} bytes ({size}) once decompressed, more than {budget}"));
    }
    Ok(())
}
