//! Let ONNX Runtime map a network's weights from its file instead of copying them.
//!
//! From a single-file ONNX model, ONNX Runtime parses the whole protobuf and copies every weight
//! into its own buffers: for the reference U-Net (31 M parameters, 118 MB) a 0.17-0.3 s load
//! with a transient peak of 1.3-1.5 x the model, and 130 MB resident per session. Weights
//! stored as ONNX *external data* it maps instead (0.04 s, about 20 MB until the first
//! inference touches the pages). [`skeleton`] gets that for an ordinary
//! single-file model without touching it: it rewrites the model's small skeleton so that each
//! large inline weight becomes external data whose location is the model file itself, at the
//! offset where its bytes already are. The engine hands ONNX Runtime the skeleton (45 KB for
//! the U-Net) and the model's directory; the file on disk is never changed.
//!
//! The rewrite works on the protobuf wire format and touches only the top-level graph's
//! `raw_data` initializers of at least [`MIN_MAPPED_BYTES`]: every other field, known to this
//! build's ONNX schema or not, is copied with its value unchanged (keys and lengths re-encoded
//! in their minimal form). Weights held elsewhere (`float_data`, Constant nodes, subgraphs) are
//! read and kept in the skeleton, so ONNX Runtime copies those as before.

use prost::encoding::encode_varint;
use std::io::{Read, Seek};

/// Smallest weight worth a mapping: smaller ones (biases, norm scales) stay in the skeleton.
pub const MIN_MAPPED_BYTES: usize = 4096;

// Field numbers from onnx.proto.
const MODEL_GRAPH: u64 = 7;
const GRAPH_INITIALIZER: u64 = 5;
const TENSOR_RAW_DATA: u64 = 9;
const TENSOR_EXTERNAL_DATA: u64 = 13;
const TENSOR_DATA_LOCATION: u64 = 14;
const ENTRY_KEY: u64 = 1;
const ENTRY_VALUE: u64 = 2;
const LOCATION_EXTERNAL: u64 = 1;

const WIRE_VARINT: u64 = 0;
const WIRE_FIXED64: u64 = 1;
const WIRE_LEN: u64 = 2;
const WIRE_FIXED32: u64 = 5;

/// A protobuf reader over a file that skips the payloads it does not copy, so that building a
/// skeleton reads only the model's small parts, not its weights.
struct Wire<R: Read + Seek> {
    r: std::io::BufReader<R>,
    pos: u64,
}

impl<R: Read + Seek> Wire<R> {
    fn byte(&mut self) -> Result<u8, String> {
        let mut b = [0u8; 1];
        self.r.read_exact(&mut b).map_err(|e| format!("reading at byte {}: {e}", self.pos))?;
        self.pos += 1;
        Ok(b[0])
    }

    fn varint(&mut self) -> Result<u64, String> {
        let mut value = 0u64;
        for shift in (0..64).step_by(7) {
            let b = self.byte()?;
            // The tenth byte holds bit 63 only.
            if shift == 63 && b > 1 {
                break;
            }
            value |= u64::from(b & 0x7f) << shift;
            if b < 0x80 {
                return Ok(value);
            }
        }
        Err(format!("malformed varint before byte {}", self.pos))
    }

    /// A field's key and, for a length-delimited one, its length, checked to end by `end`.
    fn key(&mut self, end: u64) -> Result<(u64, u64, u64), String> {
        let key = self.varint()?;
        let (number, wire) = (key >> 3, key & 7);
        if number == 0 {
            return Err(format!("field number 0 at byte {}", self.pos));
        }
        let len = if wire == WIRE_LEN { self.varint()? } else { 0 };
        if len > end.saturating_sub(self.pos) {
            return Err(format!("field {number} runs past the end of its message"));
        }
        Ok((number, wire, len))
    }

    /// After a field: it must have ended within its message.
    fn within(&self, number: u64, end: u64) -> Result<(), String> {
        if self.pos > end {
            return Err(format!("field {number} runs past the end of its message"));
        }
        Ok(())
    }

    fn bytes(&mut self, n: u64) -> Result<Vec<u8>, String> {
        let mut b = vec![0u8; n as usize];
        self.r.read_exact(&mut b).map_err(|e| format!("reading at byte {}: {e}", self.pos))?;
        self.pos += n;
        Ok(b)
    }

    fn skip(&mut self, n: u64) -> Result<(), String> {
        self.r.seek_relative(n as i64).map_err(|e| format!("seeking past byte {}: {e}", self.pos))?;
        self.pos += n;
        Ok(())
    }

    /// Copy a field whose key has been read (`len`: its length if length-delimited), re-encoded.
    /// Returns its value for a varint.
    fn copy(&mut self, number: u64, wire: u64, len: u64, out: &mut Vec<u8>) -> Result<u64, String> {
        match wire {
            WIRE_LEN => {
                let payload = self.bytes(len)?;
                put_len(out, number, &payload);
                Ok(0)
            }
            WIRE_VARINT => {
                let v = self.varint()?;
                encode_varint(number << 3 | WIRE_VARINT, out);
                encode_varint(v, out);
                Ok(v)
            }
            WIRE_FIXED64 | WIRE_FIXED32 => {
                encode_varint(number << 3 | wire, out);
                out.extend(self.bytes(if wire == WIRE_FIXED64 { 8 } else { 4 })?);
                Ok(0)
            }
            other => Err(format!("unsupported protobuf wire type {other} (field {number})")),
        }
    }
}

fn put_len(out: &mut Vec<u8>, number: u64, payload: &[u8]) {
    encode_varint(number << 3 | WIRE_LEN, out);
    encode_varint(payload.len() as u64, out);
    out.extend_from_slice(payload);
}

fn entry(key: &str, value: &str) -> Vec<u8> {
    let mut e = Vec::new();
    put_len(&mut e, ENTRY_KEY, key.as_bytes());
    put_len(&mut e, ENTRY_VALUE, value.as_bytes());
    e
}

/// A model's skeleton: the model with its large inline weights as references into its file.
#[derive(Debug, Clone, PartialEq)]
pub struct Skeleton {
    pub bytes: Vec<u8>,
    /// Weights referenced, and their bytes.
    pub weights: usize,
    pub weight_bytes: u64,
}

/// Whether a weight at this file offset may be handed to ONNX Runtime where it lies. Payload
/// offsets in a protobuf file are arbitrary (a third of the bytes of the shipped and benchmark
/// U-Nets start 4-byte aligned), and ONNX Runtime maps external data at any offset. x86-64 and
/// AArch64 load misaligned floats correctly (outputs identical to ONNX Runtime's own loading,
/// tested); elsewhere (32-bit ARM faults on them) only 8-byte aligned weights are mapped.
fn mappable(offset: u64) -> bool {
    cfg!(any(target_arch = "x86_64", target_arch = "aarch64")) || offset % 8 == 0
}

/// The skeleton of the ONNX model in `file` (`len` bytes, named `file_name` in its directory):
/// every inline initializer of the top-level graph of at least `min_bytes` becomes external
/// data at its own offset in that file. Reads only what it copies.
pub fn skeleton(file: impl Read + Seek, len: u64, file_name: &str, min_bytes: usize) -> Result<Skeleton, String> {
    let mut w = Wire { r: std::io::BufReader::new(file), pos: 0 };
    let mut out = Skeleton { bytes: Vec::with_capacity(64 << 10), weights: 0, weight_bytes: 0 };
    let mut graphs = 0;
    while w.pos < len {
        let (number, wire, n) = w.key(len)?;
        if number == MODEL_GRAPH && wire == WIRE_LEN {
            graphs += 1;
            let end = w.pos + n;
            let mut graph = Vec::with_capacity(64 << 10);
            while w.pos < end {
                let (number, wire, n) = w.key(end)?;
                if number == GRAPH_INITIALIZER && wire == WIRE_LEN {
                    let tensor_end = w.pos + n;
                    let tensor = tensor_skeleton(&mut w, tensor_end, file_name, min_bytes, &mut out)?;
                    put_len(&mut graph, GRAPH_INITIALIZER, &tensor);
                } else {
                    w.copy(number, wire, n, &mut graph)?;
                    w.within(number, end)?;
                }
            }
            put_len(&mut out.bytes, MODEL_GRAPH, &graph);
        } else {
            w.copy(number, wire, n, &mut out.bytes)?;
            w.within(number, len)?;
        }
    }
    if graphs != 1 {
        return Err(format!("expected one graph, found {graphs}"));
    }
    Ok(out)
}

/// Where a tensor's (last) `raw_data` is: kept among its copied fields, or left in the file.
enum Raw {
    Copied(usize),
    InFile { offset: u64, length: u64 },
}

/// One initializer (a `TensorProto` ending at `end`), its raw data referenced if large enough.
/// The meaning is kept as protobuf and ONNX Runtime read it: of repeated `raw_data` fields the
/// last counts, and a tensor marked external reads its side file whatever `raw_data` it has.
fn tensor_skeleton<R: Read + Seek>(w: &mut Wire<R>, end: u64, file_name: &str, min_bytes: usize, stats: &mut Skeleton) -> Result<Vec<u8>, String> {
    let mut fields: Vec<(u64, Vec<u8>)> = Vec::new();
    let (mut raw, mut external) = (None, false);
    while w.pos < end {
        let (number, wire, n) = w.key(end)?;
        if number == TENSOR_RAW_DATA && wire == WIRE_LEN {
            if let Some(Raw::Copied(i)) = raw {
                fields[i].1.clear(); // superseded
            }
            if n >= min_bytes.max(1) as u64 && mappable(w.pos) {
                raw = Some(Raw::InFile { offset: w.pos, length: n });
                w.skip(n)?;
                continue;
            }
            raw = Some(Raw::Copied(fields.len()));
        }
        let mut f = Vec::new();
        let value = w.copy(number, wire, n, &mut f)?;
        w.within(number, end)?;
        if number == TENSOR_DATA_LOCATION && wire == WIRE_VARINT {
            external = value == LOCATION_EXTERNAL;
        }
        fields.push((number, f));
    }
    let mut out: Vec<u8> = Vec::new();
    let in_file = match raw {
        Some(Raw::InFile { offset, length }) if !external => Some((offset, length)),
        _ => None,
    };
    let Some((offset, length)) = in_file else {
        // Unchanged, except that a tensor marked external loses the raw data ONNX Runtime ignores.
        for (number, f) in &fields {
            if !(external && *number == TENSOR_RAW_DATA) {
                out.extend_from_slice(f);
            }
        }
        return Ok(out);
    };
    for (_, f) in fields.iter().filter(|(n, _)| *n != TENSOR_EXTERNAL_DATA && *n != TENSOR_DATA_LOCATION) {
        out.extend_from_slice(f);
    }
    put_len(&mut out, TENSOR_EXTERNAL_DATA, &entry("location", file_name));
    put_len(&mut out, TENSOR_EXTERNAL_DATA, &entry("offset", &offset.to_string()));
    put_len(&mut out, TENSOR_EXTERNAL_DATA, &entry("length", &length.to_string()));
    encode_varint(TENSOR_DATA_LOCATION << 3 | WIRE_VARINT, &mut out);
    encode_varint(LOCATION_EXTERNAL, &mut out);
    stats.weights += 1;
    stats.weight_bytes += length;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::encoding::decode_varint;

    /// A field of a message held in memory (test-side parser, independent of `Wire`).
    struct Field<'a> {
        number: u64,
        payload: &'a [u8],
        varint: u64,
    }

    fn fields(message: &[u8]) -> Vec<Field<'_>> {
        try_fields(message).expect("a well-formed test message")
    }

    /// `None` for a malformed message (the fuzz test meets copied, mutated payloads).
    fn try_fields(message: &[u8]) -> Option<Vec<Field<'_>>> {
        let mut out = Vec::new();
        let mut rest = message;
        while !rest.is_empty() {
            let key = decode_varint(&mut rest).ok()?;
            let (mut payload, mut varint): (&[u8], u64) = (&[], 0);
            match key & 7 {
                WIRE_VARINT => varint = decode_varint(&mut rest).ok()?,
                WIRE_LEN => {
                    let len = decode_varint(&mut rest).ok()? as usize;
                    if len > rest.len() {
                        return None;
                    }
                    payload = &rest[..len];
                    rest = &rest[len..];
                }
                WIRE_FIXED64 | WIRE_FIXED32 => {
                    let n = if key & 7 == WIRE_FIXED64 { 8 } else { 4 };
                    rest = rest.get(n..)?;
                }
                _ => return None,
            }
            out.push(Field { number: key >> 3, payload, varint });
        }
        Some(out)
    }

    fn build(file: &[u8]) -> Result<Skeleton, String> {
        skeleton(std::io::Cursor::new(file), file.len() as u64, "net.onnx", MIN_MAPPED_BYTES)
    }

    const TENSOR_NAME: u64 = 8;

    fn tensor(name: &str, raw: &[u8]) -> Vec<u8> {
        let mut t = Vec::new();
        encode_varint(1 << 3, &mut t); // dims
        encode_varint(raw.len() as u64 / 4, &mut t);
        encode_varint(2 << 3, &mut t); // data_type FLOAT
        encode_varint(1, &mut t);
        put_len(&mut t, TENSOR_NAME, name.as_bytes());
        put_len(&mut t, TENSOR_RAW_DATA, raw);
        t
    }

    fn external(name: &str) -> Vec<u8> {
        let mut t = Vec::new();
        put_len(&mut t, TENSOR_NAME, name.as_bytes());
        put_len(&mut t, TENSOR_EXTERNAL_DATA, &entry("location", "elsewhere.data"));
        encode_varint(TENSOR_DATA_LOCATION << 3 | WIRE_VARINT, &mut t);
        encode_varint(LOCATION_EXTERNAL, &mut t);
        t
    }

    fn model(tensors: &[Vec<u8>]) -> Vec<u8> {
        let mut g = Vec::new();
        put_len(&mut g, 2, b"graph-name"); // GraphProto.name: copied through
        for t in tensors {
            put_len(&mut g, GRAPH_INITIALIZER, t);
        }
        let mut m = Vec::new();
        encode_varint(1 << 3, &mut m); // ir_version
        encode_varint(9, &mut m);
        put_len(&mut m, MODEL_GRAPH, &g);
        put_len(&mut m, 999, b"an unknown field survives");
        m
    }

    fn text(f: &Field<'_>) -> String {
        String::from_utf8(f.payload.to_vec()).unwrap()
    }

    #[test]
    fn large_weights_refer_to_their_own_bytes_in_the_file_and_the_rest_is_kept() {
        let big: Vec<u8> = (0..10_000u32).map(|i| (i % 251) as u8).collect();
        let big2: Vec<u8> = (0..5_000u32).map(|i| (i % 13) as u8).collect();
        let small = vec![7u8; 16];
        let file = model(&[tensor("w0", &big), tensor("b0", &small), external("e0"), tensor("w1", &big2)]);
        let sk = build(&file).unwrap();
        assert_eq!((sk.weights, sk.weight_bytes), (2, 15_000));
        assert!(sk.bytes.len() < 400, "the skeleton holds no large weight: {} bytes", sk.bytes.len());
        let top = fields(&sk.bytes);
        assert!(top.iter().any(|f| f.number == 999 && f.payload == b"an unknown field survives"));
        let graph = top.iter().find(|f| f.number == MODEL_GRAPH).unwrap().payload;
        let gf = fields(graph);
        assert!(gf.iter().any(|f| f.number == 2 && f.payload == b"graph-name"));
        let inits: Vec<_> = gf.into_iter().filter(|f| f.number == GRAPH_INITIALIZER).collect();
        assert_eq!(inits.len(), 4);
        for (init, original) in inits.iter().zip([Some(&big), Some(&small), None, Some(&big2)]) {
            let fs = fields(init.payload);
            let ext: Vec<(String, String)> = fs
                .iter()
                .filter(|f| f.number == TENSOR_EXTERNAL_DATA)
                .map(|f| {
                    let kv = fields(f.payload);
                    (text(&kv[0]), text(&kv[1]))
                })
                .collect();
            let Some(original) = original else {
                assert_eq!(ext, [("location".to_string(), "elsewhere.data".to_string())], "an external weight is left as it was");
                continue;
            };
            if original.len() < MIN_MAPPED_BYTES {
                assert!(ext.is_empty());
                assert_eq!(fs.iter().find(|f| f.number == TENSOR_RAW_DATA).unwrap().payload, &original[..]);
                continue;
            }
            assert!(fs.iter().all(|f| f.number != TENSOR_RAW_DATA));
            assert!(fs.iter().any(|f| f.number == TENSOR_DATA_LOCATION && f.varint == LOCATION_EXTERNAL));
            assert!(fs.iter().any(|f| f.number == TENSOR_NAME), "the name is kept");
            let get = |k: &str| ext.iter().find(|(key, _)| key == k).unwrap().1.clone();
            assert_eq!(get("location"), "net.onnx");
            let (offset, length): (usize, usize) = (get("offset").parse().unwrap(), get("length").parse().unwrap());
            assert_eq!(&file[offset..offset + length], &original[..], "the reference points at the weight's own bytes");
        }
        // Nothing large enough: the skeleton is the model, re-encoded field for field.
        let small_model = model(&[tensor("b0", &small)]);
        let sk = build(&small_model).unwrap();
        assert_eq!((sk.weights, &sk.bytes), (0, &small_model));
    }

    #[test]
    fn repeated_raw_data_and_external_markers_keep_their_meaning() {
        let big: Vec<u8> = (0..8_000u32).map(|i| (i % 7) as u8).collect();
        let small = vec![3u8; 8];
        let with = |parts: &[(u64, &[u8])], location: bool| {
            let mut t = Vec::new();
            put_len(&mut t, TENSOR_NAME, b"t");
            for (number, payload) in parts {
                put_len(&mut t, *number, payload);
            }
            if location {
                encode_varint(TENSOR_DATA_LOCATION << 3 | WIRE_VARINT, &mut t);
                encode_varint(LOCATION_EXTERNAL, &mut t);
            }
            model(&[t])
        };
        let tensor_fields = |sk: &Skeleton| {
            let top = fields(&sk.bytes);
            let graph = top.iter().find(|f| f.number == MODEL_GRAPH).unwrap().payload;
            let init = fields(graph).into_iter().find(|f| f.number == GRAPH_INITIALIZER).unwrap().payload.to_vec();
            init
        };
        // Large then small raw_data: the small one counts; nothing is mapped.
        let sk = build(&with(&[(TENSOR_RAW_DATA, &big), (TENSOR_RAW_DATA, &small)], false)).unwrap();
        let t = tensor_fields(&sk);
        let raws: Vec<Vec<u8>> = fields(&t).iter().filter(|f| f.number == TENSOR_RAW_DATA).map(|f| f.payload.to_vec()).collect();
        assert_eq!((sk.weights, raws), (0, vec![small.clone()]));
        // Small then large: the large one counts and is mapped; the small one is gone.
        let file = with(&[(TENSOR_RAW_DATA, &small), (TENSOR_RAW_DATA, &big)], false);
        let sk = build(&file).unwrap();
        let t = tensor_fields(&sk);
        assert_eq!(sk.weights, 1);
        assert!(fields(&t).iter().all(|f| f.number != TENSOR_RAW_DATA));
        // Marked external with raw_data too: ONNX Runtime reads the side file, so the tensor
        // keeps its external fields, loses the ignored raw data and is not re-pointed.
        let side = entry("location", "side.data");
        let sk = build(&with(&[(TENSOR_RAW_DATA, &big), (TENSOR_EXTERNAL_DATA, &side)], true)).unwrap();
        let t = tensor_fields(&sk);
        let fs = fields(&t);
        assert_eq!(sk.weights, 0);
        assert!(fs.iter().all(|f| f.number != TENSOR_RAW_DATA));
        assert!(fs.iter().any(|f| f.number == TENSOR_EXTERNAL_DATA && f.payload == &side[..]));
        assert!(fs.iter().any(|f| f.number == TENSOR_DATA_LOCATION && f.varint == LOCATION_EXTERNAL));
    }

    #[test]
    fn fields_that_overrun_their_message_are_errors() {
        // A tensor whose declared length ends inside its last varint field.
        let mut t = Vec::new();
        put_len(&mut t, TENSOR_NAME, b"t");
        encode_varint(2 << 3, &mut t); // data_type
        encode_varint(300, &mut t); // two bytes
        let mut g = Vec::new();
        encode_varint(GRAPH_INITIALIZER << 3 | WIRE_LEN, &mut g);
        encode_varint(t.len() as u64 - 1, &mut g); // one byte short
        g.extend_from_slice(&t);
        let mut m = Vec::new();
        put_len(&mut m, MODEL_GRAPH, &g);
        let e = build(&m).unwrap_err();
        assert!(e.contains("past the end"), "{e}");
        // A length near 2^64 neither overflows nor allocates.
        let mut m = Vec::new();
        encode_varint(MODEL_GRAPH << 3 | WIRE_LEN, &mut m);
        encode_varint(u64::MAX - 3, &mut m);
        assert!(build(&m).unwrap_err().contains("past the end"));
        // Field number 0 and an over-long varint.
        assert!(build(&[0x02, 0x00]).unwrap_err().contains("field number 0"));
        assert!(build(&[0x08, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x7f]).unwrap_err().contains("malformed varint"));
    }

    #[test]
    fn mutated_models_never_panic_and_every_reference_stays_in_the_file() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let big: Vec<u8> = (0..6_000u32).map(|i| (i % 251) as u8).collect();
        let original = model(&[tensor("w0", &big), tensor("b0", &[1, 2, 3, 4]), external("e0"), tensor("w1", &big)]);
        let (mut ok, mut refused) = (0, 0);
        for trial in 0..3000 {
            let mut file = original.clone();
            match trial % 3 {
                0 => file.truncate(rng.gen_range(0..file.len())),
                1 => {
                    for _ in 0..rng.gen_range(1..4) {
                        let i = rng.gen_range(0..file.len());
                        file[i] ^= 1 << rng.gen_range(0..8);
                    }
                }
                _ => {
                    let i = rng.gen_range(0..file.len());
                    file[i] = rng.gen();
                }
            }
            let Ok(sk) = build(&file) else {
                refused += 1;
                continue;
            };
            ok += 1;
            // Every reference the skeleton makes lies inside the file it was built from.
            let graph = fields(&sk.bytes).into_iter().find(|f| f.number == MODEL_GRAPH).unwrap().payload.to_vec();
            for init in fields(&graph).into_iter().filter(|f| f.number == GRAPH_INITIALIZER) {
                let entries: Vec<(String, String)> = fields(init.payload)
                    .iter()
                    .filter(|f| f.number == TENSOR_EXTERNAL_DATA)
                    .filter_map(|f| {
                        // Entries copied from a mutated file may be malformed: not ours to check.
                        let kv = try_fields(f.payload)?;
                        let s = |i: usize| kv.get(i).map(|f| String::from_utf8_lossy(f.payload).into_owned());
                        Some((s(0)?, s(1)?))
                    })
                    .collect();
                if entries.iter().any(|(k, v)| k == "location" && v == "net.onnx") {
                    let get = |k: &str| entries.iter().find(|(key, _)| key == k).unwrap().1.parse::<usize>().unwrap();
                    assert!(get("offset") + get("length") <= file.len(), "trial {trial}: a reference past the end of the file");
                }
            }
        }
        assert!(ok > 100 && refused > 100, "both outcomes occur: {ok} read, {refused} refused");
    }

    #[test]
    fn corrupt_models_are_errors() {
        let mut bytes = model(&[tensor("w0", &vec![1u8; 8192])]);
        bytes.truncate(bytes.len() - 40); // cuts into the graph
        let e = build(&bytes).unwrap_err();
        assert!(e.contains("past the end"), "{e}");
        assert!(build(b"").unwrap_err().contains("one graph"));
        let e = build(b"\x08").unwrap_err();
        assert!(e.contains("reading at byte 1"), "{e}");
    }
}
