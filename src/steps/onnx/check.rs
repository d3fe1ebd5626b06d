//! An ONNX network's file checked before anything loads it: its graph's signature (inputs,
//! outputs, shapes) decoded from the protobuf without the weights, and the external weight
//! files it names, so that a wrong or damaged series is an error naming the file.

use crate::steps::error::OnnxError;
use crate::{Error, Result};
use std::path::Path;

/// A network content error as the crate's error.
pub(super) fn invalid(path: &Path, message: impl Into<String>) -> Error {
    OnnxError::Invalid { path: path.to_path_buf(), message: message.into() }.into()
}

/// The declared shape of a network's single input and output, read from the ONNX file without
/// building the network: checked before imaging starts.
#[derive(Debug, Clone, PartialEq)]
pub struct Signature {
    /// Dimensions; `None` for a symbolic one.
    pub input: Vec<Option<i64>>,
    pub output: Vec<Option<i64>>,
    /// Names of the input's symbolic dimensions (`Some("H")`), parallel to `input`: ONNX
    /// Runtime is told their values, so it plans memory for the one shape it will see.
    pub input_params: Vec<Option<String>>,
    /// Bytes of weights already held in external-data side files.
    pub external_bytes: u64,
    /// For ONNX Runtime: the model's skeleton with its large inline weights referring to their
    /// own bytes in the file, which it then maps instead of copying (`mapped_weights`), and
    /// the file's length and modification time it was made from. `None`: nothing to map.
    pub mapped: Option<MappedWeights>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct MappedWeights {
    pub skeleton: std::sync::Arc<Vec<u8>>,
    pub weights: usize,
    pub bytes: u64,
    stamp: (u64, Option<std::time::SystemTime>),
}

impl MappedWeights {
    /// Whether the network file changed since its weights were mapped (its size or time).
    pub(super) fn is_stale(&self, path: &Path) -> bool {
        file_stamp(path).ok() != Some(self.stamp)
    }
}

fn file_stamp(path: &Path) -> std::io::Result<(u64, Option<std::time::SystemTime>)> {
    let m = std::fs::metadata(path)?;
    Ok((m.len(), m.modified().ok()))
}

/// The parts of an ONNX `ModelProto` the check needs. Decoding only these skips the weights'
/// bytes instead of copying them (a full decode of the 31 M-parameter U-Net took 0.18 s per
/// file, which a 15-network series paid before imaging). Field numbers are onnx.proto's.
#[derive(Clone, PartialEq, prost::Message)]
struct ModelHead {
    #[prost(message, optional, tag = "7")]
    graph: Option<GraphHead>,
}

#[derive(Clone, PartialEq, prost::Message)]
struct GraphHead {
    #[prost(message, repeated, tag = "5")]
    initializer: Vec<TensorName>,
    #[prost(message, repeated, tag = "11")]
    input: Vec<tract_onnx::pb::ValueInfoProto>,
    #[prost(message, repeated, tag = "12")]
    output: Vec<tract_onnx::pb::ValueInfoProto>,
}

/// A `TensorProto`'s name and where its data lives; the data fields are skipped.
#[derive(Clone, PartialEq, prost::Message)]
struct TensorName {
    #[prost(string, tag = "8")]
    name: String,
    #[prost(message, repeated, tag = "13")]
    external_data: Vec<StringEntry>,
    /// 1 = EXTERNAL: the weights are in the file `external_data` names.
    #[prost(int32, tag = "14")]
    data_location: i32,
}

#[derive(Clone, PartialEq, prost::Message)]
struct StringEntry {
    #[prost(string, tag = "1")]
    key: String,
    #[prost(string, tag = "2")]
    value: String,
}

/// Every external weight's side file exists beside the model and holds the bytes the model
/// says it does: a missing or truncated `.data` file fails here, before imaging starts.
/// Returns the bytes held externally.
fn check_external_data(path: &Path, initializers: &[TensorName]) -> Result<u64> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut sizes: std::collections::HashMap<String, u64> = std::collections::HashMap::new();
    let mut total = 0;
    for t in initializers.iter().filter(|t| t.data_location == 1) {
        let get = |k: &str| t.external_data.iter().find(|e| e.key == k).map(|e| e.value.as_str());
        let bad = |what: String| invalid(path, format!("weight '{}': {what}", t.name));
        let location = get("location").ok_or_else(|| bad("external data without a location".into()))?;
        let number = |k: &str| get(k).map(|v| v.parse::<u64>().map_err(|_| bad(format!("external data {k} '{v}' is not a number")))).transpose();
        let (offset, length) = (number("offset")?.unwrap_or(0), number("length")?);
        if Path::new(location).components().any(|c| !matches!(c, std::path::Component::Normal(_))) {
            return Err(bad(format!("external data location '{location}' must be a file name beside the model")));
        }
        let size = match sizes.get(location) {
            Some(s) => *s,
            None => {
                let file = dir.join(location);
                let missing = |source| OnnxError::MissingWeights { path: file.clone(), network: path.to_path_buf(), source };
                let s = std::fs::metadata(&file).map_err(missing)?.len();
                *sizes.entry(location.to_string()).or_insert(s)
            }
        };
        let end = offset.checked_add(length.unwrap_or(size.saturating_sub(offset))).ok_or_else(|| bad(format!("external data offset {offset} is out of range")))?;
        if end > size {
            return Err(invalid(&dir.join(location), format!("truncated: weight '{}' of {} needs bytes {offset}..{end}, the file has {size}", t.name, path.display())));
        }
        total += end - offset;
    }
    Ok(total)
}

/// The graph's head, read from the model's skeleton (`mapped_weights`: only the small parts of
/// the file are read), and the skeleton itself when it maps any weight.
fn read_graph_head(path: &Path) -> Result<(GraphHead, Option<MappedWeights>)> {
    let unreadable = |what, source: Box<dyn std::error::Error + Send + Sync>| OnnxError::Unreadable { path: path.to_path_buf(), what, source };
    let stamp = file_stamp(path).map_err(|e| unreadable("cannot read the network", e.into()))?;
    let file = std::fs::File::open(path).map_err(|e| unreadable("cannot read the network", e.into()))?;
    // A name ONNX Runtime cannot be given exactly (not UTF-8) is loaded the ordinary way: the
    // skeleton keeps every weight (minimum size beyond any file).
    let name = path.file_name().and_then(|n| n.to_str()).filter(|_| path.parent().is_none_or(|d| d.to_str().is_some()));
    let min_bytes = if name.is_some() { super::mapped_weights::MIN_MAPPED_BYTES } else { usize::MAX };
    let skeleton = super::mapped_weights::skeleton(file, stamp.0, name.unwrap_or_default(), min_bytes)
        .map_err(|e| unreadable("not a readable ONNX model", e.into()))?;
    let head = <ModelHead as prost::Message>::decode(skeleton.bytes.as_slice()).map_err(|e| unreadable("not a readable ONNX model", e.into()))?;
    let graph = head.graph.ok_or_else(|| invalid(path, "ONNX model without a graph"))?;
    let mapped = (skeleton.weights > 0).then(|| MappedWeights {
        weights: skeleton.weights,
        bytes: skeleton.weight_bytes,
        skeleton: std::sync::Arc::new(skeleton.bytes),
        stamp,
    });
    Ok((graph, mapped))
}

/// Read and check an R2D2 network file: one float32 input `[1, 2, H, W]`, one float32 output
/// `[1, 1, H, W]` (H and W fixed or symbolic; fixed ones must equal `size`).
pub fn check_network(path: &Path, size: usize) -> Result<Signature> {
    use tract_onnx::pb::type_proto::Value as TypeValue;
    use tract_onnx::pb::tensor_shape_proto::dimension::Value as Dim;
    let (graph, mapped) = read_graph_head(path)?;
    // Older exporters list the weights among the inputs too.
    let weights: std::collections::HashSet<&str> = graph.initializer.iter().map(|t| t.name.as_str()).collect();
    let inputs: Vec<_> = graph.input.iter().filter(|i| !weights.contains(i.name.as_str())).collect();
    if inputs.len() != 1 || graph.output.len() != 1 {
        return Err(invalid(path, format!("expected one input and one output, found {} inputs and {} outputs", inputs.len(), graph.output.len())));
    }
    let shape_of = |v: &tract_onnx::pb::ValueInfoProto, what: &str| -> Result<Vec<Option<i64>>> {
        let Some(TypeValue::TensorType(t)) = v.r#type.as_ref().and_then(|t| t.value.as_ref()) else {
            return Err(invalid(path, format!("{what} '{}' is not a tensor", v.name)));
        };
        // 1 = FLOAT in onnx.proto's TensorProto.DataType.
        if t.elem_type != 1 {
            return Err(invalid(path, format!("{what} '{}': expected float32 elements, got ONNX data type {}", v.name, t.elem_type)));
        }
        let dims = t.shape.as_ref().map(|s| s.dim.iter().map(|d| match d.value {
            Some(Dim::DimValue(n)) => Some(n),
            _ => None,
        }).collect()).unwrap_or_default();
        Ok(dims)
    };
    let input = shape_of(inputs[0], "input")?;
    let input_params = match inputs[0].r#type.as_ref().and_then(|t| t.value.as_ref()) {
        Some(TypeValue::TensorType(t)) => t.shape.as_ref().map(|s| s.dim.iter().map(|d| match &d.value {
            Some(Dim::DimParam(name)) if !name.is_empty() => Some(name.clone()),
            _ => None,
        }).collect()).unwrap_or_default(),
        _ => Vec::new(),
    };
    let output = shape_of(&graph.output[0], "output")?;
    let check = |dims: &[Option<i64>], channels: i64, what: &str| -> Result<()> {
        let expected = format!("[1, {channels}, H, W]");
        let shown = format!("[{}]", dims.iter().map(|d| d.map_or("?".into(), |n| n.to_string())).collect::<Vec<_>>().join(", "));
        if dims.len() != 4 {
            return Err(invalid(path, format!("{what}: expected rank 4 {expected}, got rank {} {shown}", dims.len())));
        }
        let ok = |d: Option<i64>, want: i64| d.is_none() || d == Some(want);
        if !ok(dims[0], 1) || !ok(dims[1], channels) {
            return Err(invalid(path, format!("{what}: expected {expected}, got {shown}")));
        }
        for d in &dims[2..] {
            if let Some(n) = d {
                if *n != size as i64 {
                    return Err(invalid(path, format!("{what}: the network has a fixed image size {shown}, but the pipeline images {size} x {size}")));
                }
            }
        }
        Ok(())
    };
    check(&input, 2, "input")?;
    check(&output, 1, "output")?;
    // The skeleton's own references into the model file are checked with the rest.
    let external_bytes = check_external_data(path, &graph.initializer)?.saturating_sub(mapped.as_ref().map_or(0, |m| m.bytes));
    Ok(Signature { input, output, input_params, external_bytes, mapped })
}
