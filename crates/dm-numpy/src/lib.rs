//! numpy data read without Python: a numpy-aware unpickler ([`pickle`]) and
//! the raw array decoding it shares with `.npy` readers ([`ndarray_raw`]).
//! Both are parsers of outside input: every malformed file is an error,
//! never a panic.

pub mod ndarray_raw;
pub mod pickle;

pub use ndarray_raw::{ArrayData, ByteOrder, Element, NdArray};
pub use pickle::{Limits, PickleError, Value};
