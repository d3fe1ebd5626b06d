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
                let read = |body: &arrow::buffer::Buffer, batch| read_record_batch(body, batch, schema.clone(), &self.dictionaries, None, &version);
                let batch = match decompress_body(&body, batch, "record batch")? {
                    None => read(&body, batch),
                    Some((buffers, body)) => {
                        let mut fbb = flatbuffers::FlatBufferBuilder::new();
                        let uncompressed = uncompressed_batch(&mut fbb, batch, &buffers);
                        fbb.finish_minimal(uncompressed);
                        read(&body, flatbuffers::root::<arrow::ipc::RecordBatch>(fbb.finished_data()).map_err(|e| e.to_string())?)
                    }
                };
                batch.map(IpcMessage::Batch).map_err(|e| e.to_string())
            }
            MessageHeader::DictionaryBatch => {
                let schema = schema.ok_or("a dictionary before the schema")?;
                let dictionary = message.header_as_dictionary_batch().ok_or_else(|| missing("dictionary"))?;
                let decompressed = match dictionary.data() {
                    Some(batch) => decompress_body(&body, batch, "dictionary")?.map(|(buffers, body)| (batch, buffers, body)),
                    None => None,
                };
                let read = match decompressed {
                    None => read_dictionary(&body, dictionary, schema, &mut self.dictionaries, &version),
                    Some((batch, buffers, body)) => {
                        let mut fbb = flatbuffers::FlatBufferBuilder::new();
                        let data = Some(uncompressed_batch(&mut fbb, batch, &buffers));
                        let args = arrow::ipc::DictionaryBatchArgs { id: dictionary.id(), data, isDelta: dictionary.isDelta() };
                        let uncompressed = arrow::ipc::DictionaryBatch::create(&mut fbb, &args);
                        fbb.finish_minimal(uncompressed);
                        let dictionary = flatbuffers::root::<arrow::ipc::DictionaryBatch>(fbb.finished_data()).map_err(|e| e.to_string())?;
                        read_dictionary(&body, dictionary, schema, &mut self.dictionaries, &version)
                    }
                };
                read.map_err(|e| e.to_string())?;
                Ok(IpcMessage::Other)
            }
            MessageHeader::NONE => Ok(IpcMessage::Other),
            other => Err(format!("unexpected {other:?} message (a visibility table has a schema and record batches)")),
        }
    }
}

/// How a compressed batch's buffer is stored: its first 8 bytes declare its length once
/// decompressed, -1 meaning stored as it is (after the 8 bytes), 0 empty.
enum Stored {
    Empty,
    Raw,
    Compressed(usize),
}

/// The body of a compressed (LZ4 or ZSTD) batch decompressed, and its buffers' places there;
/// `None` for an uncompressed batch. arrow's decoder would size each buffer by the length its
/// first 8 bytes declare and then decompress to the end of the stream, however far past that
/// it goes (a buffer of a few kilobytes can hold gigabytes of zstd output): here the declared
/// lengths are summed and checked against the memory budget before anything is allocated, and
/// each buffer must decompress to exactly what it declares, decoding stopped one byte past it.
fn decompress_body(body: &[u8], batch: arrow::ipc::RecordBatch<'_>, what: &str) -> std::result::Result<Option<(Vec<arrow::ipc::Buffer>, arrow::buffer::Buffer)>, String> {
    use arrow::ipc::CompressionType;
    let Some(compression) = batch.compression() else {
        return Ok(None);
    };
    let codec = match compression.codec() {
        CompressionType::LZ4_FRAME => "LZ4",
        CompressionType::ZSTD => "ZSTD",
        other => return Err(format!("a {what} compressed with codec {other:?}: expected LZ4_FRAME or ZSTD")),
    };
    let mut stored = Vec::new();
    let mut total = 0u64;
    for (k, buffer) in batch.buffers().into_iter().flatten().enumerate() {
        let (offset, length) = (buffer.offset(), buffer.length());
        let range = usize::try_from(offset)
            .ok()
            .zip(usize::try_from(length).ok())
            .and_then(|(start, length)| Some(start..start.checked_add(length)?))
            .filter(|range| range.end <= body.len())
            .ok_or_else(|| format!("buffer {k} of the {what} (offset {offset}, {length} bytes) lies outside its body of {} bytes", body.len()))?;
        let kind = match range.len() {
            0 => Stored::Empty,
            1..=7 => return Err(format!("buffer {k} of the compressed {what} has {} bytes, fewer than the 8 that declare its length", range.len())),
            _ => match i64::from_le_bytes(body[range.start..range.start + 8].try_into().expect("8 bytes")) {
                -1 => Stored::Raw,
                0 => Stored::Empty,
                declared => {
                    let declared = u64::try_from(declared).map_err(|_| format!("buffer {k} of the compressed {what} declares a length of {declared} bytes"))?;
                    total = total.saturating_add(declared);
                    Stored::Compressed(usize::try_from(declared).unwrap_or(usize::MAX))
                }
            },
        };
        if matches!(kind, Stored::Raw) {
            total = total.saturating_add(range.len() as u64 - 8);
        }
        total = total.saturating_add(7); // each buffer starts 8-aligned
        stored.push((range, kind));
    }
    let budget = crate::limits::memory_budget();
    if total > budget.bytes {
        let size = crate::limits::format_bytes(total as f64);
        return Err(format!("a compressed {what} declares {total} bytes ({size}) once decompressed, more than {budget}"));
    }
    let mut out = arrow::buffer::MutableBuffer::new(0);
    let mut buffers = Vec::with_capacity(stored.len());
    for (k, (range, kind)) in stored.into_iter().enumerate() {
        out.resize(out.len().next_multiple_of(8), 0);
        let start = out.len();
        let data = &body[range];
        match kind {
            Stored::Empty => {}
            Stored::Raw => out.extend_from_slice(&data[8..]),
            Stored::Compressed(declared) => {
                out.resize(start + declared, 0);
                decompress_exactly(codec, &data[8..], &mut out.as_slice_mut()[start..])
                    .map_err(|why| format!("buffer {k} of the {what} ({codec}-compressed, {} bytes) {why}", data.len()))?;
            }
        }
        buffers.push(arrow::ipc::Buffer::new(start as i64, (out.len() - start) as i64));
    }
    Ok(Some((buffers, out.into())))
}

/// Decompresses `input` into `out`, which must be exactly what it decompresses to.
fn decompress_exactly(codec: &str, input: &[u8], out: &mut [u8]) -> std::result::Result<(), String> {
    let mut reader: Box<dyn Read + '_> = match codec {
        "LZ4" => Box::new(lz4_flex::frame::FrameDecoder::new(input)),
        _ => Box::new(zstd::Decoder::with_buffer(input).map_err(|e| format!("does not decompress: {e}"))?),
    };
    let mut got = 0;
    let mut past = [0u8; 1];
    loop {
        let into = if got < out.len() { &mut out[got..] } else { &mut past[..] };
        match reader.read(into) {
            Ok(0) => break,
            Ok(_) if got == out.len() => {
                return Err(format!("decompresses to more than the {} bytes it declares (a damaged file, or one made to exhaust memory)", out.len()));
            }
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(format!("does not decompress: {e}")),
        }
    }
    if got < out.len() {
        return Err(format!("decompresses to {got} bytes, fewer than the {} it declares", out.len()));
    }
    Ok(())
}

/// `batch`'s flatbuffer with `buffers` in place of its own and no compression: the batch as
/// [`decompress_body`] left it.
fn uncompressed_batch<'f>(fbb: &mut flatbuffers::FlatBufferBuilder<'f>, batch: arrow::ipc::RecordBatch<'_>, buffers: &[arrow::ipc::Buffer]) -> flatbuffers::WIPOffset<arrow::ipc::RecordBatch<'f>> {
    let nodes: Vec<arrow::ipc::FieldNode> = batch.nodes().map(|nodes| nodes.iter().copied().collect()).unwrap_or_default();
    let variadic: Option<Vec<i64>> = batch.variadicBufferCounts().map(|counts| counts.iter().collect());
    let args = arrow::ipc::RecordBatchArgs {
        length: batch.length(),
        nodes: Some(fbb.create_vector(&nodes)),
        buffers: Some(fbb.create_vector(buffers)),
        compression: None,
        variadicBufferCounts: variadic.map(|counts| fbb.create_vector(&counts)),
    };
    arrow::ipc::RecordBatch::create(fbb, &args)
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::ipc::writer::{IpcWriteOptions, StreamWriter};
    use arrow::ipc::CompressionType;

    /// An Arrow IPC stream of a 4096-sample table in batches of 1024, its buffers compressed
    /// (those that compression makes smaller: the others are stored as they are).
    fn compressed_stream(codec: CompressionType) -> Vec<u8> {
        use super::super::table::{tests::test_table, to_record_batches};
        let t = test_table(4096);
        let (schema, batches) = to_record_batches(&t, &ObservationMeta::new(10.0, 20.0, "VLA"), 1024).unwrap();
        let options = IpcWriteOptions::default().try_with_compression(Some(codec)).unwrap();
        let mut writer = StreamWriter::try_new_with_options(Vec::new(), &schema, options).unwrap();
        for batch in &batches {
            writer.write(batch).unwrap();
        }
        writer.finish().unwrap();
        writer.into_inner().unwrap()
    }

    /// `stream` with the buffers of its first record batch replaced by what `change` makes of
    /// them (each as stored: its 8-byte length, then the compressed bytes), laid out again.
    fn with_first_batch_buffers(stream: &[u8], change: impl FnOnce(&mut Vec<Vec<u8>>)) -> Vec<u8> {
        let mut out = Vec::new();
        let (mut at, mut change) = (0, Some(change));
        while at < stream.len() {
            assert_eq!(stream[at..at + 4], CONTINUATION);
            let length = i32::from_le_bytes(stream[at + 4..at + 8].try_into().unwrap()) as usize;
            if length == 0 {
                out.extend_from_slice(&stream[at..]);
                break;
            }
            let header = &stream[at + 8..at + 8 + length];
            let message = arrow::ipc::root_as_message(header).unwrap();
            let body = &stream[at + 8 + length..at + 8 + length + message.bodyLength() as usize];
            let next = at + 8 + length + body.len();
            let batch = message.header_as_record_batch().filter(|_| change.is_some());
            let Some(batch) = batch else {
                out.extend_from_slice(&stream[at..next]);
                at = next;
                continue;
            };
            let mut buffers: Vec<Vec<u8>> = batch.buffers().unwrap().iter().map(|b| body[b.offset() as usize..(b.offset() + b.length()) as usize].to_vec()).collect();
            (change.take().unwrap())(&mut buffers);
            let (mut new_body, mut places) = (Vec::new(), Vec::new());
            for bytes in &buffers {
                places.push(arrow::ipc::Buffer::new(new_body.len() as i64, bytes.len() as i64));
                new_body.extend_from_slice(bytes);
                new_body.resize(new_body.len().next_multiple_of(8), 0);
            }
            let mut fbb = flatbuffers::FlatBufferBuilder::new();
            let nodes: Vec<arrow::ipc::FieldNode> = batch.nodes().unwrap().iter().copied().collect();
            let compression = batch.compression().unwrap();
            let compression = arrow::ipc::BodyCompression::create(&mut fbb, &arrow::ipc::BodyCompressionArgs { codec: compression.codec(), method: compression.method() });
            let args = arrow::ipc::RecordBatchArgs {
                length: batch.length(),
                nodes: Some(fbb.create_vector(&nodes)),
                buffers: Some(fbb.create_vector(&places)),
                compression: Some(compression),
                variadicBufferCounts: None,
            };
            let batch = arrow::ipc::RecordBatch::create(&mut fbb, &args);
            let args = arrow::ipc::MessageArgs {
                version: message.version(),
                header_type: MessageHeader::RecordBatch,
                header: Some(batch.as_union_value()),
                bodyLength: new_body.len() as i64,
                custom_metadata: None,
            };
            let message = arrow::ipc::Message::create(&mut fbb, &args);
            fbb.finish_minimal(message);
            let mut header = fbb.finished_data().to_vec();
            header.resize(header.len().next_multiple_of(8), 0);
            out.extend_from_slice(&CONTINUATION);
            out.extend_from_slice(&(header.len() as i32).to_le_bytes());
            out.extend_from_slice(&header);
            out.extend_from_slice(&new_body);
            at = next;
        }
        out
    }

    /// A zstd frame that decompresses to `blocks` x 128 KiB of zeros: each block is stored as
    /// one byte repeated (an RLE block, 4 bytes in all), so 32 KiB of it make 1 GiB.
    fn zstd_bomb(blocks: usize) -> Vec<u8> {
        let mut frame = 0xfd2f_b528u32.to_le_bytes().to_vec();
        // Frame header: no content size, no checksum; a window of 128 KiB (2^(10 + 7)).
        frame.extend_from_slice(&[0x00, 7 << 3]);
        for k in 0..blocks {
            let last = u32::from(k + 1 == blocks);
            let header = (128 << 10) << 3 | 1 << 1 | last;
            frame.extend_from_slice(&header.to_le_bytes()[..3]);
            frame.push(0);
        }
        frame
    }

    /// Every batch of the stream `bytes`, read from a file: the first error.
    fn read(bytes: &[u8]) -> Result<u64> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("in.arrows");
        std::fs::write(&path, bytes).unwrap();
        let mut reader = IpcReader::open(path.to_str().unwrap(), false)?;
        let mut rows = 0;
        while let Some(batch) = reader.next_batch() {
            rows += batch?.num_rows() as u64;
        }
        Ok(rows)
    }

    #[test]
    fn compressed_buffers_read_as_the_uncompressed_table() {
        let plain = read(&compressed_stream(CompressionType::LZ4_FRAME)).unwrap();
        assert_eq!(plain, 4096);
        for codec in [CompressionType::LZ4_FRAME, CompressionType::ZSTD] {
            // Laid out again unchanged, the batch still reads (the rewriting is sound).
            let same = with_first_batch_buffers(&compressed_stream(codec), |_| {});
            assert_eq!(read(&same).unwrap(), 4096, "{codec:?}");
        }
    }

    /// A buffer whose first 8 bytes declare 2^40 bytes once decompressed is refused before
    /// anything is allocated; one that declares 8 bytes and holds a zstd frame of 256 MiB (a
    /// decompression bomb: arrow decoded to the end of the frame, however far, before comparing)
    /// is refused once decoding passes the 8 bytes, naming the buffer and what it declares; one
    /// that decompresses to fewer bytes than it declares too.
    #[test]
    fn compressed_buffers_must_decompress_to_what_they_declare() {
        let stream = compressed_stream(CompressionType::ZSTD);
        let compressed = |buffers: &mut Vec<Vec<u8>>| -> usize {
            buffers.iter().position(|b| b.len() > 8 && i64::from_le_bytes(b[..8].try_into().unwrap()) > 0).expect("a compressed buffer")
        };
        let declaring = |length: i64| {
            with_first_batch_buffers(&stream, |buffers| {
                let k = compressed(buffers);
                let buffer = &mut buffers[k];
                buffer[..8].copy_from_slice(&length.to_le_bytes());
            })
        };
        let e = read(&declaring(1 << 40)).unwrap_err().to_string();
        assert!(e.contains("in.arrows") && e.contains("declares 1099511") && e.contains("(1.1 TB) once decompressed, more than"), "{e}");
        let e = read(&declaring(1 << 20)).unwrap_err().to_string();
        assert!(e.contains("in.arrows") && e.contains("ZSTD-compressed") && e.contains("fewer than the 1048576 it declares"), "{e}");
        let bomb = with_first_batch_buffers(&stream, |buffers| {
            let k = compressed(buffers);
            buffers[k] = 8i64.to_le_bytes().to_vec();
            buffers[k].extend(zstd_bomb(2048));
        });
        let e = read(&bomb).unwrap_err().to_string();
        assert!(e.contains("in.arrows") && e.contains("decompresses to more than the 8 bytes it declares"), "{e}");
    }
}
