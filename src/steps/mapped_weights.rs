//! Let ONNX Runtime map a network's weights from its file instead of copying them.
//!
//! From a single-file ONNX model, ONNX Runtime parses the whole protobuf and copies every weight
//! into its own buffers: for the reference U-Net (31 M parameters, 118 MB) a 0.17-0.3 s load
//! with a transient peak of 1.3-1.5 x the model, and 130 MB resident per session. Weights
//! stored as ONNX *external data* it maps instead (0.04 s, about 20 MB until the first
//! inference touches the pages). [`reference_inline_weights`] gets that for an ordinary
//! single-file model without touching it: it rewrites the model's small skeleton so that each
//! large inline weight becomes external data whose location is the model file itself, at the
//! offset where its bytes already are. The engine hands ONNX Runtime the skeleton (45 KB for
//! the U-Net) and the model's directory; the file on disk is never changed.
//!
//! The rewrite works on the protobuf wire format and touches only the top-level graph's
//! initializers: every other field, known to this build's ONNX schema or not, is copied byte
//! for byte.

use prost::encoding::{decode_varint, encode_varint};

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

/// One protobuf field: its number, wire type and the bytes it spans (key included), plus the
/// payload for length-delimited fields.
struct Field<'a> {
    number: u64,
    wire: u64,
    whole: &'a [u8],
    payload: &'a [u8],
    varint: u64,
}

fn fields(message: &[u8]) -> std::result::Result<Vec<Field<'_>>, String> {
    let mut out = Vec::new();
    let mut rest = message;
    while !rest.is_empty() {
        let start = rest;
        let key = decode_varint(&mut rest).map_err(|e| e.to_string())?;
        let (number, wire) = (key >> 3, key & 7);
        let (mut payload, mut varint): (&[u8], u64) = (&[], 0);
        match wire {
            WIRE_VARINT => varint = decode_varint(&mut rest).map_err(|e| e.to_string())?,
            WIRE_FIXED64 | WIRE_FIXED32 => {
                let n = if wire == WIRE_FIXED64 { 8 } else { 4 };
                if rest.len() < n {
                    return Err("truncated fixed-width field".into());
                }
                rest = &rest[n..];
            }
            WIRE_LEN => {
                let len = decode_varint(&mut rest).map_err(|e| e.to_string())? as usize;
                if rest.len() < len {
                    return Err(format!("field {number} runs past the end of its message"));
                }
                payload = &rest[..len];
                rest = &rest[len..];
            }
            other => return Err(format!("unsupported protobuf wire type {other} (field {number})")),
        }
        let whole = &start[..start.len() - rest.len()];
        out.push(Field { number, wire, whole, payload, varint });
    }
    Ok(out)
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

/// The skeleton of `model` (the bytes of a file named `file_name`) in which every inline
/// initializer of at least `min_bytes` refers to its own bytes inside that file; `None` when
/// no weight qualifies (nothing to gain). Returns the skeleton, the weights referenced and
/// their bytes.
pub fn reference_inline_weights(model: &[u8], file_name: &str, min_bytes: usize) -> Result<Option<(Vec<u8>, usize, u64)>, String> {
    let base = model.as_ptr() as usize;
    // Where a payload starts in the file: its slice lies inside `model`.
    let offset_of = |payload: &[u8]| payload.as_ptr() as usize - base;
    let (mut count, mut bytes) = (0usize, 0u64);
    let mut out = Vec::with_capacity(64 << 10);
    let mut graphs = 0;
    for f in fields(model)? {
        if f.number != MODEL_GRAPH || f.wire != WIRE_LEN {
            out.extend_from_slice(f.whole);
            continue;
        }
        graphs += 1;
        let mut graph = Vec::with_capacity(64 << 10);
        for g in fields(f.payload)? {
            let tensor = if g.number == GRAPH_INITIALIZER && g.wire == WIRE_LEN { Some(fields(g.payload)?) } else { None };
            let raw = tensor.as_ref().and_then(|t| {
                let external = t.iter().any(|f| f.number == TENSOR_DATA_LOCATION && f.varint == LOCATION_EXTERNAL);
                t.iter().find(|f| f.number == TENSOR_RAW_DATA && f.wire == WIRE_LEN && f.payload.len() >= min_bytes.max(1)).filter(|_| !external)
            });
            let (Some(t), Some(raw)) = (&tensor, raw) else {
                graph.extend_from_slice(g.whole);
                continue;
            };
            let mut skeleton = Vec::with_capacity(g.payload.len().min(4096) + 128);
            for f in t.iter().filter(|f| f.number != TENSOR_RAW_DATA && f.number != TENSOR_EXTERNAL_DATA && f.number != TENSOR_DATA_LOCATION) {
                skeleton.extend_from_slice(f.whole);
            }
            put_len(&mut skeleton, TENSOR_EXTERNAL_DATA, &entry("location", file_name));
            put_len(&mut skeleton, TENSOR_EXTERNAL_DATA, &entry("offset", &offset_of(raw.payload).to_string()));
            put_len(&mut skeleton, TENSOR_EXTERNAL_DATA, &entry("length", &raw.payload.len().to_string()));
            encode_varint(TENSOR_DATA_LOCATION << 3 | WIRE_VARINT, &mut skeleton);
            encode_varint(LOCATION_EXTERNAL, &mut skeleton);
            put_len(&mut graph, GRAPH_INITIALIZER, &skeleton);
            count += 1;
            bytes += raw.payload.len() as u64;
        }
        put_len(&mut out, MODEL_GRAPH, &graph);
    }
    if graphs != 1 {
        return Err(format!("expected one graph, found {graphs}"));
    }
    Ok((count > 0).then_some((out, count, bytes)))
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let (skeleton, count, bytes) = reference_inline_weights(&file, "net.onnx", MIN_MAPPED_BYTES).unwrap().unwrap();
        assert_eq!((count, bytes), (2, 15_000));
        assert!(skeleton.len() < 400, "the skeleton holds no large weight: {} bytes", skeleton.len());
        let top = fields(&skeleton).unwrap();
        assert!(top.iter().any(|f| f.number == 999 && f.payload == b"an unknown field survives"));
        let graph = top.iter().find(|f| f.number == MODEL_GRAPH).unwrap().payload;
        let gf = fields(graph).unwrap();
        assert!(gf.iter().any(|f| f.number == 2 && f.payload == b"graph-name"));
        let inits: Vec<_> = gf.into_iter().filter(|f| f.number == GRAPH_INITIALIZER).collect();
        assert_eq!(inits.len(), 4);
        for (init, original) in inits.iter().zip([Some(&big), Some(&small), None, Some(&big2)]) {
            let fs = fields(init.payload).unwrap();
            let ext: Vec<(String, String)> = fs
                .iter()
                .filter(|f| f.number == TENSOR_EXTERNAL_DATA)
                .map(|f| {
                    let kv = fields(f.payload).unwrap();
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
        // Nothing large enough: nothing to gain.
        assert!(reference_inline_weights(&model(&[tensor("b0", &small)]), "net.onnx", MIN_MAPPED_BYTES).unwrap().is_none());
    }

    #[test]
    fn corrupt_models_are_errors() {
        let mut bytes = model(&[tensor("w0", &vec![1u8; 8192])]);
        bytes.truncate(bytes.len() - 40); // cuts into the graph
        let e = reference_inline_weights(&bytes, "bad.onnx", MIN_MAPPED_BYTES).unwrap_err();
        assert!(e.contains("past the end"), "{e}");
        assert!(reference_inline_weights(b"", "empty.onnx", MIN_MAPPED_BYTES).unwrap_err().contains("one graph"));
    }
}
