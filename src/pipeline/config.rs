//! Pipeline YAML: parsing, command-line overrides, and errors that point at the file, line
//! and column of the problem.
//!
//! ```yaml
//! name: quickstart
//! image: {size: 256, superresolution: 1.5}   # shared by weighting, gridder and steps
//! stages:
//!   source: {kind: simulate, to: weights, ...}
//!   weights: {kind: weighting, scheme: briggs, robust: 0, to: grid}
//!   grid: {kind: gridder, to: step}
//!   step: {kind: clean, to: update}
//!   update: {kind: residual, method: toeplitz, to: step, done: write}
//!   write: {kind: writer, prefix: "out/{job}"}
//! ```
//!
//! The image geometry is pipeline-wide rather than a gridder option: weighting, gridder and
//! a trained network series must all agree on it, so it is stated once.

use super::located::{self, ROUTING_KEYS};
use crate::{Error, Result};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_yaml::{Mapping, Value};
use std::path::{Path, PathBuf};
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPipeline {
    #[serde(default)]
    name: Option<String>,
    /// Threads for numerical work in each stage (0: all cores).
    #[serde(default)]
    threads: usize,
    /// Capacity of the channels between stages (jobs in flight per edge).
    #[serde(default)]
    channel_capacity: Option<usize>,
    #[serde(default)]
    image: Value,
    stages: Mapping,
}

/// The typed parameters of a stage kind: what a Rust program writes instead of a stage's YAML
/// mapping ([`StageSpec::typed`]), and what the kind reads back (`BuildContext::params`).
/// Serialised, they are the mapping the YAML would hold (without `kind`, `to`, `done`, which
/// belong to the engine and are no parameter's name).
///
/// The built-in kinds' parameters are in `r2d2_imaging::params`; a kind of an embedding
/// program's own implements this for its parameters the same way.
pub trait StageParams: Serialize + DeserializeOwned + Clone + Send + Sync + 'static {
    /// The YAML `kind` these parameters are for.
    const KIND: &'static str;
}

/// One stage as written in the YAML: its name, kind, routing and its own parameters.
///
/// The parameters are a YAML mapping, whatever the kind: the registry is open to kinds the
/// engine does not know, so the spec carries any kind's. A spec written in code with
/// [`StageSpec::typed`] also keeps the typed value, which its kind then receives as it was
/// given (the mapping is what it reads as, for logs and the kinds that read it).
#[derive(Clone, Debug)]
pub struct StageSpec {
    pub name: String,
    pub kind: String,
    pub to: Option<String>,
    pub done: Option<String>,
    /// The remaining keys, parsed by the stage kind's own config struct.
    params: Value,
    typed: Option<TypedParams>,
}

/// A stage's parameters as the program gave them ([`StageSpec::typed`]).
#[derive(Clone)]
struct TypedParams(std::sync::Arc<dyn std::any::Any + Send + Sync>);

impl std::fmt::Debug for TypedParams {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("TypedParams")
    }
}

/// A parsed pipeline description.
#[derive(Clone, Debug)]
pub struct PipelineSpec {
    pub file: PathBuf,
    text: String,
    pub name: String,
    pub threads: usize,
    pub channel_capacity: usize,
    pub image: Value,
    /// Stages in file order.
    pub stages: Vec<StageSpec>,
    /// The `--set` overrides applied to the text, to tell a value of the file from one of the
    /// command line in errors.
    overrides: Vec<String>,
}

impl StageSpec {
    /// A stage of `P`'s kind with typed parameters, e.g.
    /// `StageSpec::typed("weights", &WeightingParams::default())?.to("grid")`. An error only if
    /// the parameters do not serialise to a mapping (which the built-in kinds' always do).
    pub fn typed<P: StageParams>(name: impl Into<String>, params: &P) -> Result<StageSpec> {
        let name = name.into();
        let what = || format!("stage '{name}' ({})", P::KIND);
        let mapping = serde_yaml::to_value(params).map_err(|e| Error::parameter(what(), format!("its parameters do not serialise: {e}")))?;
        match &mapping {
            Value::Mapping(map) if ROUTING_KEYS.iter().any(|k| map.contains_key(*k)) => {
                Err(Error::parameter(what(), format!("its parameters use a name the engine keeps for routing ({})", ROUTING_KEYS.join(", "))))
            }
            Value::Mapping(_) => {
                let typed = Some(TypedParams(std::sync::Arc::new(params.clone())));
                Ok(StageSpec { name, kind: P::KIND.to_string(), to: None, done: None, params: mapping, typed })
            }
            _ => Err(Error::parameter(what(), "its parameters serialise to something other than a mapping")),
        }
    }

    /// A stage from its parameters, a mapping with its `kind` (as it would be written in YAML).
    pub fn new(name: impl Into<String>, params: Value) -> StageSpec {
        let mut params = params;
        let kind = params.as_mapping_mut().and_then(|m| m.remove("kind")).and_then(|k| k.as_str().map(str::to_string)).unwrap_or_default();
        StageSpec { name: name.into(), kind, to: None, done: None, params, typed: None }
    }

    /// The stage's parameters as a YAML mapping (without `kind`, `to` and `done`).
    pub fn params(&self) -> &Value {
        &self.params
    }

    /// Sets one parameter (`key: value` in the stage's mapping); a typed value the spec held
    /// gives way to the mapping, which the kind then reads.
    pub fn set_param(&mut self, key: &str, value: impl Into<Value>) -> Result<()> {
        let Value::Mapping(map) = &mut self.params else {
            return Err(Error::parameter(format!("stage '{}'", self.name), "its parameters are not a mapping"));
        };
        if ROUTING_KEYS.contains(&key) {
            return Err(Error::parameter(format!("stage '{}'", self.name), format!("`{key}` is the engine's routing, not a parameter")));
        }
        map.insert(Value::String(key.to_string()), value.into());
        self.typed = None;
        Ok(())
    }

    /// The typed value the spec was written with, if it is a `T`.
    fn typed_as<T: Clone + 'static>(&self) -> Option<T> {
        self.typed.as_ref().and_then(|t| t.0.downcast_ref::<T>()).cloned()
    }

    /// Where the stage's jobs go next.
    pub fn to(mut self, stage: impl Into<String>) -> StageSpec {
        self.to = Some(stage.into());
        self
    }

    /// Where a residual update's jobs go when the imaging loop ends.
    pub fn done(mut self, stage: impl Into<String>) -> StageSpec {
        self.done = Some(stage.into());
        self
    }
}

impl PipelineSpec {
    /// A pipeline built in code (no file: errors name the stage and key, without a line).
    pub fn new(name: impl Into<String>, image: &impl Serialize, stages: Vec<StageSpec>) -> Result<PipelineSpec> {
        let name = name.into();
        let image = serde_yaml::to_value(image).map_err(|e| Error::parameter(format!("pipeline '{name}'"), format!("its image settings do not serialise: {e}")))?;
        let file = PathBuf::from(format!("pipeline '{name}'"));
        for stage in &stages {
            if stage.kind.is_empty() {
                return Err(located(&file, None, &format!("stage '{}' has no `kind`", stage.name)));
            }
        }
        Ok(PipelineSpec { file, text: String::new(), name, threads: 0, channel_capacity: 2, image, stages, overrides: Vec::new() })
    }

    /// Read `path` and apply `overrides` (`stage.key=value`, `image.key=value`, `threads=N`).
    pub fn load(path: &Path, overrides: &[String]) -> Result<PipelineSpec> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::parse(&text, path, overrides)
    }

    pub fn parse(text: &str, file: &Path, overrides: &[String]) -> Result<PipelineSpec> {
        // A byte-order mark (Windows editors write one) is no content; serde_yaml would read it
        // as a document before the first. It holds no newline, so line numbers are unchanged.
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        check_nesting(text, file)?;
        // First pass on the text itself, so syntax and type errors carry line and column.
        let mut value: Value = serde_yaml::from_str(text).map_err(|e| yaml_error(file, &e))?;
        let raw_check: std::result::Result<RawPipeline, _> = serde_path_to_error::deserialize(
            serde_yaml::Deserializer::from_str(text),
        );
        if let Err(e) = raw_check {
            let location = e.inner().location().map(|l| (l.line(), l.column()));
            return Err(located(file, location, &format!("{}: {}", e.path(), e.inner())));
        }
        for o in overrides {
            apply_override(&mut value, o)?;
        }
        let raw: RawPipeline = serde_path_to_error::deserialize(value)
            .map_err(|e| Error::parameter("set", format!("{}: {}", e.path(), e.inner())))?;
        let mut stages = Vec::new();
        for (key, body) in raw.stages {
            let name = key
                .as_str()
                .ok_or_else(|| located(file, None, "stage names must be strings"))?
                .to_string();
            let here = locate(text, &name, None);
            let Value::Mapping(mut map) = body else {
                return Err(located(file, here, &format!("stage '{name}': expected a mapping with a `kind`")));
            };
            let mut take = |k: &str| -> Result<Option<String>> {
                match map.remove(k) {
                    None => Ok(None),
                    Some(Value::String(s)) => Ok(Some(s)),
                    Some(other) => Err(located(
                        file,
                        locate(text, &name, Some(k)),
                        &format!("stages.{name}.{k}: expected a stage name, got {}", short(&other)),
                    )),
                }
            };
            let kind = take("kind")?.ok_or_else(|| located(file, here, &format!("stage '{name}' has no `kind`")))?;
            let to = take("to")?;
            let done = take("done")?;
            stages.push(StageSpec { name, kind, to, done, params: Value::Mapping(map), typed: None });
        }
        // Before any stage is built: a size or thread count this machine cannot take would
        // otherwise surface as an aborted allocation or a hang, not as an error about the key.
        crate::limits::check_threads(raw.threads).map_err(|m| located(file, locate_top(text, "threads"), &format!("threads: {m}")))?;
        let capacity = raw.channel_capacity.unwrap_or(2);
        if !(1..=MAX_CHANNEL_CAPACITY).contains(&capacity) {
            let at = locate_top(text, "channel_capacity");
            return Err(located(file, at, &format!("channel_capacity: {capacity}: expected 1 to {MAX_CHANNEL_CAPACITY} (jobs waiting between two stages, each holding its images and perhaps its visibilities; the default is 2)")));
        }
        Ok(PipelineSpec {
            file: file.to_path_buf(),
            text: text.to_string(),
            name: raw.name.unwrap_or_else(|| file.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default()),
            threads: raw.threads,
            channel_capacity: capacity,
            image: raw.image,
            stages,
            overrides: overrides.to_vec(),
        })
    }

    /// The `image` section as `T`; errors name the file, the section's line and the key, or
    /// the `--set` override the wrong value came from.
    pub fn shared<T: DeserializeOwned>(&self) -> Result<T> {
        serde_path_to_error::deserialize(self.image.clone()).map_err(|e| {
            let path = e.path().to_string();
            let key = if path == "." { "image".to_string() } else { format!("image.{path}") };
            match self.override_of_key(&key) {
                // The file has no line for a value of the command line.
                Some(set) => Error::input(&self.file, format!("{key}, as set by the override {set}: {}", e.inner())),
                None => self.top_error("image", &format!("{key}: {}", e.inner())),
            }
        })
    }

    /// The `--set` override that gave the top-level `key` (`image.size`) its value, or a value
    /// around it (`image.size` for `image`, `image` for `image.size`).
    fn override_of_key(&self, key: &str) -> Option<&str> {
        self.overrides.iter().map(String::as_str).find(|spec| {
            let path = spec.split_once('=').map_or(*spec, |(p, _)| p);
            within(path, key) || within(key, path)
        })
    }

    /// An error about a top-level key (`image`), at its line when the spec came from a file.
    pub fn top_error(&self, key: &str, message: &str) -> Error {
        let at = if self.text.is_empty() { None } else { locate_top(&self.text, key) };
        located(&self.file, at, message)
    }

    /// Deserialize a stage's parameters into its kind's config struct; errors name the file,
    /// line, column and key (a nested key by its path: `stages.source.split_by.window`), or the
    /// `--set` override the wrong value came from.
    pub fn stage_params<T: DeserializeOwned + Clone + 'static>(&self, stage: &StageSpec) -> Result<T> {
        // Written in code: the value as given, not a copy read back from its mapping.
        if let Some(typed) = stage.typed_as::<T>() {
            return Ok(typed);
        }
        let e = match serde_path_to_error::deserialize(stage.params.clone()) {
            Ok(params) => return Ok(params),
            Err(e) => e,
        };
        let message = e.inner().to_string();
        let path = e.path().to_string();
        // Keys of a struct embedded in the parameters (`#[serde(flatten)]`): serde reports a
        // wrong value there without its key, an unknown key without the keys it expects, and
        // either where the mapping starts.
        let (key, embedded) = match failing_key(&path, &message) {
            Some(key) => (Some(key), path == "." && !message.contains(", ")),
            None => {
                let key = flattened_key::<T>(&stage.params, &message);
                let embedded = key.is_some();
                (key, embedded)
            }
        };
        let what = match &key {
            Some(k) => format!("stages.{}.{k} ({} stage)", stage.name, stage.kind),
            None => format!("stages.{} ({} stage)", stage.name, stage.kind),
        };
        if let Some(set) = self.override_of(&stage.name, key.as_deref()) {
            // The file has no line for a value of the command line.
            return Err(Error::input(&self.file, format!("{what}, as set by the override {set}: {message}")));
        }
        // The values came from the file: read them again from its text, which knows where
        // each one is (a `Value` does not). The same failure at the same key is this one.
        let in_text = || located::failure_in_text::<T>(&self.text, &stage.name).filter(|(p, _)| *p == path).and_then(|(_, at)| at);
        let at_key = || locate(&self.text, &stage.name, key.as_deref().map(|k| k.split(['.', '[']).next().unwrap_or(k)));
        let location = if embedded { at_key().or_else(in_text) } else { in_text().or_else(at_key) };
        Err(located(&self.file, location, &format!("{what}: {message}")))
    }

    /// The `--set` override that gave stage `stage`'s `key` (a path inside its parameters) its
    /// value, or a value around it.
    fn override_of(&self, stage: &str, key: Option<&str>) -> Option<&str> {
        let key = key?;
        self.overrides.iter().map(String::as_str).find(|spec| {
            let path = spec.split_once('=').map_or(*spec, |(p, _)| p);
            let mut parts = path.splitn(2, '.');
            if parts.next() != Some(stage) || TOP_KEYS.contains(&stage) {
                return false;
            }
            match parts.next() {
                None => true,
                Some(set) => within(set, key) || within(key, set),
            }
        })
    }

    /// An error about a stage (or one of its keys), located in the file.
    pub fn stage_error(&self, stage: &str, key: Option<&str>, message: &str) -> Error {
        located(&self.file, locate(&self.text, stage, key), message)
    }

    /// [`stage_error`](Self::stage_error) for an error that a stage's value led to, kept as the
    /// located error's cause (a caller matching on the module error still finds it).
    pub fn stage_error_caused(&self, stage: &str, key: Option<&str>, message: &str, cause: Error) -> Error {
        match located(&self.file, locate(&self.text, stage, key), message) {
            Error::Located { file, line, column, message, .. } => Error::Located { file, line, column, message, cause: Some(Box::new(cause)) },
            // No line to point at (a pipeline built in code): the cause itself, which names its file.
            _ => cause,
        }
    }

    pub fn stage(&self, name: &str) -> Option<&StageSpec> {
        self.stages.iter().find(|s| s.name == name)
    }
}

/// Whether the key path `inner` is `outer` or a key inside it (`a.b` and `a[0]` are inside `a`).
fn within(outer: &str, inner: &str) -> bool {
    inner == outer || inner.starts_with(&format!("{outer}.")) || inner.starts_with(&format!("{outer}["))
}

/// The top-level keys a `--set` may name (any other first part is a stage).
/// The most jobs a channel between two stages may hold: each slot holds a whole job.
pub const MAX_CHANNEL_CAPACITY: usize = 64;

const TOP_KEYS: [&str; 4] = ["image", "threads", "name", "channel_capacity"];

/// The key a deserialisation error is about, as a path inside the stage's parameters
/// (`scheme`, `split_by.window`, `hours[1]`). The path of an unknown field ends with it where
/// serde_path_to_error could record it; else the field is named in the message only.
fn failing_key(path: &str, message: &str) -> Option<String> {
    let unknown = message.strip_prefix("unknown field `").and_then(|r| r.split('`').next());
    let key = match (path, unknown) {
        (".", Some(field)) => field.to_string(),
        (_, Some(field)) if path != field && !path.ends_with(&format!(".{field}")) => format!("{path}.{field}"),
        _ => path.to_string(),
    };
    (!key.is_empty() && key != ".").then_some(key)
}

/// The key of a stage's parameters that a failure at their top (`message`) is about, where
/// serde could not say: a value of a struct the parameters embed (`#[serde(flatten)]`, as
/// `kind: ms` embeds its selection) fails with no path and a message naming no key. It is the
/// first key without which the parameters read, or fail otherwise (but for missing that key).
fn flattened_key<T: DeserializeOwned>(params: &Value, message: &str) -> Option<String> {
    let Value::Mapping(map) = params else { return None };
    map.keys().filter_map(Value::as_str).find(|key| {
        let mut without = map.clone();
        without.remove(*key);
        match serde_path_to_error::deserialize::<_, T>(Value::Mapping(without)) {
            Ok(_) => true,
            Err(e) => {
                let otherwise = e.inner().to_string();
                otherwise != message && otherwise != format!("missing field `{key}`")
            }
        }
    }).map(str::to_string)
}

/// Deepest nesting of flow collections (`[...]`, `{...}`) accepted: a pipeline needs four or
/// five levels, a plugin's configuration a few more.
const MAX_NESTING: usize = 64;

/// Refuses flow collections nested deeper than [`MAX_NESTING`], in one pass over the text,
/// before the YAML parser sees it: it takes quadratic time on deep nesting (200 KB of brackets
/// took 26 s to reject). The error names the line and column where the limit is crossed.
///
/// A bracket counts where a collection can start (at the start of a line, after white space,
/// `[`, `{` or `,`), not inside quoted scalars, comments or words like `a[1]`: a conservative
/// reading of YAML that errs toward counting less, never toward refusing a valid pipeline.
fn check_nesting(text: &str, file: &Path) -> Result<()> {
    let mut depth = 0usize;
    // The quote character of the quoted scalar being read, if any.
    let mut quote: Option<char> = None;
    for (line_index, line) in text.lines().enumerate() {
        // Whether a token may start here: at the start of the line, after white space, a comma
        // or a collection just opened (not after a word, where `[` is part of the word).
        let mut boundary = true;
        let mut chars = line.char_indices().peekable();
        while let Some((column, c)) = chars.next() {
            let mut opened = false;
            match (quote, c) {
                (Some('\''), '\'') if chars.peek().is_some_and(|&(_, next)| next == '\'') => {
                    chars.next(); // '' is a quote inside a single-quoted scalar
                }
                (Some('"'), '\\') => {
                    chars.next(); // an escape: the next character is not the closing quote
                }
                (Some(open), c) if c == open => quote = None,
                (Some(_), _) => {}
                (None, '#') if boundary => break,
                (None, '\'' | '"') if boundary => quote = Some(c),
                (None, '[' | '{') if boundary => {
                    depth += 1;
                    if depth > MAX_NESTING {
                        let here = Some((line_index + 1, column + 1));
                        return Err(located(file, here, &format!("collections nested more than {MAX_NESTING} deep: a pipeline needs a handful of levels")));
                    }
                    opened = true;
                }
                (None, ']' | '}') => depth = depth.saturating_sub(1),
                _ => {}
            }
            boundary = quote.is_none() && (opened || c.is_whitespace() || c == ',');
        }
    }
    Ok(())
}

fn short(v: &Value) -> String {
    serde_yaml::to_string(v).unwrap_or_default().trim().chars().take(40).collect()
}

fn yaml_error(file: &Path, e: &serde_yaml::Error) -> Error {
    located(file, e.location().map(|l| (l.line(), l.column())), &e.to_string())
}

fn located(file: &Path, location: Option<(usize, usize)>, message: &str) -> Error {
    match location {
        Some((line, column)) => Error::Located { file: file.to_path_buf(), line, column, message: message.to_string(), cause: None },
        None => Error::input(file, message.to_string()),
    }
}

/// Line and column (1-based) of a top-level key (`image`, `threads`).
fn locate_top(text: &str, key: &str) -> Option<(usize, usize)> {
    text.lines().position(|l| l.strip_prefix(key).is_some_and(|rest| rest.trim_start().starts_with(':'))).map(|i| (i + 1, 1))
}

/// Line and column (1-based) of stage `stage` under `stages:`, or of `key` inside it.
fn locate(text: &str, stage: &str, key: Option<&str>) -> Option<(usize, usize)> {
    let indent = |l: &str| l.len() - l.trim_start().len();
    let lines: Vec<&str> = text.lines().collect();
    let start = lines.iter().position(|l| l.trim_end() == "stages:" && indent(l) == 0)?;
    let (stage_line, stage_indent) = lines.iter().enumerate().skip(start + 1).find_map(|(i, l)| {
        let t = l.trim_start();
        (t.starts_with(&format!("{stage}:")) && indent(l) > 0).then(|| (i, indent(l)))
    })?;
    let Some(key) = key else { return Some((stage_line + 1, stage_indent + 1)) };
    // The key on the stage's own line (flow style) or on the lines nested under it.
    if let Some(col) = lines[stage_line].find(&format!("{key}:")) {
        return Some((stage_line + 1, col + 1));
    }
    for (i, l) in lines.iter().enumerate().skip(stage_line + 1) {
        if !l.trim().is_empty() && !l.trim_start().starts_with('#') && indent(l) <= stage_indent {
            break;
        }
        if l.trim_start().starts_with(&format!("{key}:")) {
            return Some((i + 1, indent(l) + 1));
        }
    }
    Some((stage_line + 1, stage_indent + 1))
}

/// `--set a.b=value`: set a key in the YAML tree (value parsed as YAML: numbers, booleans).
fn apply_override(root: &mut Value, spec: &str) -> Result<()> {
    let (path, text) = spec
        .split_once('=')
        .ok_or_else(|| Error::parameter("set", format!("expected stage.key=value, got '{spec}'")))?;
    let value: Value = serde_yaml::from_str(text)
        .map_err(|e| Error::parameter("set", format!("'{spec}': value is not valid YAML: {e}")))?;
    let parts: Vec<&str> = path.split('.').collect();
    // Stage names are looked up under `stages`; `image.*`, `threads`, `name` at the top.
    let mut node = root;
    let full: Vec<&str> = if TOP_KEYS.contains(&parts[0]) { parts.clone() } else { [&["stages"][..], &parts[..]].concat() };
    for (i, part) in full.iter().enumerate() {
        let map = node
            .as_mapping_mut()
            .ok_or_else(|| Error::parameter("set", format!("'{spec}': '{}' is not a mapping", full[..i].join("."))))?;
        let key = Value::String(part.to_string());
        if i + 1 == full.len() {
            map.insert(key, value);
            return Ok(());
        }
        if !map.contains_key(&key) {
            if i == 1 && full[0] == "stages" {
                let names: Vec<String> = map.keys().filter_map(|k| k.as_str().map(str::to_string)).collect();
                return Err(Error::parameter("set", format!("'{spec}': no stage '{part}' (stages: {})", names.join(", "))));
            }
            map.insert(key.clone(), Value::Mapping(Mapping::new()));
        }
        node = map.get_mut(&key).expect("just checked or inserted");
    }
    Err(Error::parameter("set", format!("'{spec}': empty key")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Instant;

    /// Parameters with a field the mapping does not carry: what a kind receives shows
    /// whether it came through the mapping.
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    struct Probe {
        gain: f64,
        #[serde(skip)]
        given_in_code: bool,
    }

    impl StageParams for Probe {
        const KIND: &'static str = "probe";
    }

    #[test]
    fn typed_parameters_reach_their_kind_as_given_until_a_key_is_set() {
        let given = Probe { gain: 0.1, given_in_code: true };
        let mut stage = StageSpec::typed("p", &given).unwrap();
        let pipeline = PipelineSpec::new("t", &serde_yaml::Value::Null, vec![stage.clone()]).unwrap();
        assert_eq!(pipeline.stage_params::<Probe>(&stage).unwrap(), given);
        assert_eq!(stage.params().get("gain").and_then(Value::as_f64), Some(0.1));
        // Another type than the one given is read from the mapping.
        #[derive(Clone, Deserialize)]
        struct Gain {
            gain: f64,
        }
        assert_eq!(pipeline.stage_params::<Gain>(&stage).unwrap().gain, 0.1);
        // A key set afterwards: the mapping is what the kind reads.
        stage.set_param("gain", 0.2).unwrap();
        assert_eq!(pipeline.stage_params::<Probe>(&stage).unwrap(), Probe { gain: 0.2, given_in_code: false });
        assert!(stage.set_param("to", "x").unwrap_err().to_string().contains("routing"));
    }

    /// A struct whose keys are partly those of a struct it embeds (`#[serde(flatten)]`): serde
    /// reports a wrong value of an embedded key without its path, and the error still names it.
    #[test]
    fn an_error_in_embedded_keys_names_the_key() {
        #[derive(Clone, Debug, Deserialize)]
        #[serde(deny_unknown_fields)]
        struct Outer {
            path: String,
            #[serde(flatten)]
            inner: Inner,
        }
        #[derive(Clone, Debug, Deserialize)]
        struct Inner {
            #[serde(default)]
            spw: Option<Vec<usize>>,
            #[serde(default)]
            channels: Option<[usize; 2]>,
        }
        let spec = |keys: &str| PipelineSpec::parse(&format!("stages:\n  read:\n    kind: any\n    path: a\n{keys}"), Path::new("f.yaml"), &[]).unwrap();
        let read = |keys: &str| spec(keys).stage_params::<Outer>(spec(keys).stage("read").unwrap()).map_err(|e| e.to_string());
        assert_eq!(read("    spw: [1]\n").unwrap().inner.spw, Some(vec![1]));
        assert!(read("    spw: [1]\n").unwrap().inner.channels.is_none() && read("").unwrap().path == "a");
        for (keys, key, line) in [("    channels: [1, 2]\n    spw: all\n", "spw", 6), ("    chanels: [1, 2]\n", "chanels", 5)] {
            let err = read(keys).unwrap_err();
            assert!(err.contains(&format!("stages.read.{key} (any stage)")) && err.contains(&format!("line {line}")), "{err}");
        }
        // Without a required key, that is the error: no key of the mapping is blamed.
        let bare = PipelineSpec::parse("stages:\n  read: {kind: any, spw: [1]}\n", Path::new("f.yaml"), &[]).unwrap();
        let err = bare.stage_params::<Outer>(bare.stage("read").unwrap()).unwrap_err().to_string();
        assert!(err.contains("missing field `path`") && !err.contains("stages.read.spw"), "{err}");
    }

    #[test]
    fn channel_capacity_is_bounded() {
        let text = |c: &str| format!("channel_capacity: {c}\nimage: {{size: 16}}\nstages:\n  source: {{kind: simulate}}\n");
        for bad in ["0", "65", "1000000000000", "18446744073709551615"] {
            let err = PipelineSpec::parse(&text(bad), Path::new("c.yaml"), &[]).unwrap_err().to_string();
            assert!(err.contains("c.yaml") && err.contains("line 1") && err.contains("expected 1 to 64"), "{bad}: {err}");
        }
        assert!(PipelineSpec::parse(&text("64"), Path::new("c.yaml"), &[]).is_ok());
    }

    #[test]
    fn a_byte_order_mark_is_no_content_and_moves_no_line() {
        let good = "image: {size: 16}\nstages:\n  source: {kind: simulate}\n";
        let spec = PipelineSpec::parse(&format!("\u{feff}{good}"), Path::new("bom.yaml"), &[]).unwrap();
        assert_eq!(spec.stages.len(), 1);
        assert_eq!(locate_top(&spec.text, "image"), Some((1, 1)));
        // Errors at the same lines and columns as without the mark.
        let bad = ["channel_capacity: 0\nimage: {size: 16}\nstages:\n  source: {kind: simulate}\n", "image: {size: 16}\nstages:\n  source: {kind: simulate\n"];
        for text in bad {
            let plain = PipelineSpec::parse(text, Path::new("bom.yaml"), &[]).unwrap_err().to_string();
            let marked = PipelineSpec::parse(&format!("\u{feff}{text}"), Path::new("bom.yaml"), &[]).unwrap_err().to_string();
            assert_eq!(marked, plain);
            assert!(plain.contains("line ") && !plain.contains("more than one document"), "{plain}");
        }
    }

    #[test]
    fn deep_nesting_is_refused_fast_naming_file_and_line() {
        for open in ["[", "{a: "] {
            let text = format!("image: {{size: 16}}\nstages:\n  source: {}\n", open.repeat(50_000));
            let start = Instant::now();
            let err = PipelineSpec::parse(&text, Path::new("deep.yaml"), &[]).unwrap_err().to_string();
            let seconds = start.elapsed().as_secs_f64();
            assert!(seconds < 1.0, "{open:?} x 50 000 took {seconds:.1} s to refuse");
            assert!(err.contains("deep.yaml") && err.contains("line 3") && err.contains("nested"), "{err}");
        }
    }

    #[test]
    fn brackets_in_quotes_comments_and_words_are_not_nesting() {
        let many = "[".repeat(200);
        let text = format!(
            "image: {{size: 16}}  # {many}\nstages:\n  source: {{kind: simulate, to: w}}\n  w: {{kind: writer, prefix: \"out{many}/{{job}}\"}}\n  x: 'it''s {many}'\n"
        );
        let err = PipelineSpec::parse(&text, Path::new("ok.yaml"), &[]).err().map(|e| e.to_string()).unwrap_or_default();
        assert!(!err.contains("nested"), "{err}");
        let words = format!("image: {{size: 16}}\nname: a{many}\nstages:\n  source: {{kind: simulate, to: w}}\n  w: {{kind: writer}}\n");
        PipelineSpec::parse(&words, Path::new("ok.yaml"), &[]).unwrap();
    }
}
