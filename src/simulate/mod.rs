//! Synthetic data for training and testing: procedural ground-truth skies (`sky`) and
//! Earth-rotation uv coverage from real antenna layouts (`telescope`).
//!
//! Like the other numerical modules these know nothing of files or configuration: the
//! antenna tables are compiled into the binary, and every random choice comes from a
//! caller-supplied seed so a data set can be regenerated bit for bit.

pub mod observe;
pub mod sky;
pub mod telescope;
