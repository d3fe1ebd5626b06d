//! Where in a pipeline's YAML text a stage's parameters fail to deserialise.
//!
//! A stage's parameters travel as a `serde_yaml::Value`, which has forgotten where each value
//! was written. When they fail to deserialise, the stage is read again from the text itself,
//! into the same type: serde_yaml then marks the failure with its line and column (the value's
//! for a wrong value, the key's for an unknown key, nested ones included).

use serde::de::{self, DeserializeOwned, DeserializeSeed, IgnoredAny, IntoDeserializer, MapAccess, Visitor};
use std::cell::RefCell;
use std::fmt;
use std::marker::PhantomData;

/// Keys of a stage's mapping that the engine reads (its kind and routing), not the kind.
pub(crate) const ROUTING_KEYS: [&str; 3] = ["kind", "to", "done"];

/// Deserialises stage `stage`'s parameters (its mapping under `stages:`, less `kind`, `to` and
/// `done`) from `text` as `T`. On failure: the failing path inside the parameters (as
/// `serde_path_to_error` writes it) and the line and column (1-based) where serde_yaml saw it.
/// `None` if they deserialise, or if the text fails elsewhere (it was parsed before).
pub(crate) fn failure_in_text<T: DeserializeOwned>(text: &str, stage: &str) -> Option<(String, Option<(usize, usize)>)> {
    let path = RefCell::new(None);
    let seed = Key { name: "stages", then: Key { name: stage, then: Params::<T> { path: &path, _t: PhantomData } } };
    let error = seed.deserialize(serde_yaml::Deserializer::from_str(text)).err()?;
    let path = path.into_inner()?;
    Some((path, error.location().map(|l| (l.line(), l.column()))))
}

/// Finds key `name` of a mapping and deserialises its value with `then`, skipping the others.
struct Key<'a, S> {
    name: &'a str,
    then: S,
}

impl<'de, S: DeserializeSeed<'de, Value = ()>> DeserializeSeed<'de> for Key<'_, S> {
    type Value = ();
    fn deserialize<D: de::Deserializer<'de>>(self, deserializer: D) -> Result<(), D::Error> {
        deserializer.deserialize_map(self)
    }
}

impl<'de, S: DeserializeSeed<'de, Value = ()>> Visitor<'de> for Key<'_, S> {
    type Value = ();
    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "a mapping with `{}`", self.name)
    }
    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        let mut then = Some(self.then);
        while let Some(key) = map.next_key::<String>()? {
            match then.take() {
                Some(seed) if key == self.name => map.next_value_seed(seed)?,
                seed => {
                    then = seed;
                    map.next_value::<IgnoredAny>()?;
                }
            }
        }
        Ok(())
    }
}

/// Deserialises a stage's mapping as `T`, without the routing keys, recording the failing path.
struct Params<'a, T> {
    path: &'a RefCell<Option<String>>,
    _t: PhantomData<T>,
}

impl<'de, T: DeserializeOwned> DeserializeSeed<'de> for Params<'_, T> {
    type Value = ();
    fn deserialize<D: de::Deserializer<'de>>(self, deserializer: D) -> Result<(), D::Error> {
        deserializer.deserialize_map(self)
    }
}

impl<'de, T: DeserializeOwned> Visitor<'de> for Params<'_, T> {
    type Value = ();
    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("a stage's mapping")
    }
    fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<(), A::Error> {
        let params = de::value::MapAccessDeserializer::new(WithoutRouting { map });
        serde_path_to_error::deserialize::<_, T>(params).map(drop).map_err(|e| {
            *self.path.borrow_mut() = Some(e.path().to_string());
            e.into_inner()
        })
    }
}

/// A stage's mapping less its routing keys, which are the engine's, not the kind's.
struct WithoutRouting<A> {
    map: A,
}

impl<'de, A: MapAccess<'de>> MapAccess<'de> for WithoutRouting<A> {
    type Error = A::Error;
    fn next_key_seed<K: DeserializeSeed<'de>>(&mut self, seed: K) -> Result<Option<K::Value>, A::Error> {
        let mut seed = Some(seed);
        loop {
            match self.map.next_key_seed(RoutingOr { seed: &mut seed })? {
                None => return Ok(None),
                Some(Some(key)) => return Ok(Some(key)),
                Some(None) => {
                    self.map.next_value::<IgnoredAny>()?;
                }
            }
        }
    }
    fn next_value_seed<V: DeserializeSeed<'de>>(&mut self, seed: V) -> Result<V::Value, A::Error> {
        self.map.next_value_seed(seed)
    }
}

/// A key: `None` for a routing key, else the key as `seed` reads it. The key goes to `seed`
/// from inside the YAML deserialiser's own visit, so that an unknown one is marked at its line.
struct RoutingOr<'a, K> {
    seed: &'a mut Option<K>,
}

impl<'de, K: DeserializeSeed<'de>> DeserializeSeed<'de> for RoutingOr<'_, K> {
    type Value = Option<K::Value>;
    fn deserialize<D: de::Deserializer<'de>>(self, deserializer: D) -> Result<Self::Value, D::Error> {
        deserializer.deserialize_str(self)
    }
}

impl<'de, K: DeserializeSeed<'de>> Visitor<'de> for RoutingOr<'_, K> {
    type Value = Option<K::Value>;
    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("a parameter name")
    }
    fn visit_str<E: de::Error>(self, key: &str) -> Result<Self::Value, E> {
        if ROUTING_KEYS.contains(&key) {
            return Ok(None);
        }
        let seed = self.seed.take().ok_or_else(|| E::custom("a key was read twice"))?;
        seed.deserialize(key.into_deserializer()).map(Some)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Debug, Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct P {
        #[serde(default)]
        n: usize,
        #[serde(default)]
        inner: Option<Inner>,
    }

    #[derive(Debug, Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Inner {
        x: f64,
    }

    const TEXT: &str = "image: {size: 8}\nstages:\n  a:\n    kind: k\n    n: 3\n    to: b\n  b:\n    kind: k\n    inner: {x: 1}\n";

    #[test]
    fn valid_parameters_have_no_failure() {
        assert_eq!(failure_in_text::<P>(TEXT, "a"), None);
        assert_eq!(failure_in_text::<P>(TEXT, "b"), None);
    }

    #[test]
    fn failures_are_marked_at_their_key_or_value() {
        let at = |text: &str, stage| failure_in_text::<P>(text, stage).expect("a failure");
        assert_eq!(at(&TEXT.replace("n: 3", "n: three"), "a"), ("n".into(), Some((5, 8))));
        assert_eq!(at(&TEXT.replace("n: 3", "m: 3"), "a"), ("m".into(), Some((5, 5))));
        assert_eq!(at(&TEXT.replace("{x: 1}", "{x: one}"), "b"), ("inner.x".into(), Some((9, 16))));
        assert_eq!(at(&TEXT.replace("{x: 1}", "{x: 1, y: 2}"), "b"), ("inner.y".into(), Some((9, 19))));
    }
}
