//! A numpy-aware unpickler for the data files of capture pipelines.
//!
//! `pickle.dump` of dicts, lists and tuples of numpy arrays, numpy scalars and
//! Python scalars/strings, protocols 2 to 5. General pickle readers (such as
//! serde-pickle) lose numpy's dtype, shape and memory order, because numpy
//! arrays are pickled as calls: `_reconstruct(ndarray, (0,), b'b')` followed by
//! a BUILD with the state `(version, shape, dtype, is_fortran, raw bytes)`, or,
//! under protocol 5, `_frombuffer(buffer, dtype, shape, order)`. This module
//! runs those opcodes on a small object arena and recognises exactly these
//! callables (see [`Callable`]); any other global is refused, so a pickle can
//! never make us do anything but build data.
//!
//! Hostile input is expected: every malformed pickle is an error, never a
//! panic; lengths are checked against the bytes actually present before
//! anything is allocated; shared references are expanded into the owned
//! [`Value`] tree only within node, depth and byte budgets ([`Limits`]).

use std::collections::HashMap;
use std::fmt;

use crate::ndarray_raw::{ByteOrder, Element, NdArray, parse_descriptor};

/// Bounds on what a pickle may make us allocate or build.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Largest accepted pickle, bytes.
    pub max_input_bytes: usize,
    /// Deepest container nesting of the result (also stops cycles).
    pub max_depth: usize,
    /// Most values in the result, a shared value counting once per use.
    pub max_nodes: usize,
    /// Most array and byte-string bytes in the result, shared ones counting per use.
    pub max_result_bytes: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            // A PhysTwin final_data.pkl is tens of MB; 4 GiB leaves ample room
            // while keeping a hostile size field from mattering.
            max_input_bytes: 4 << 30,
            max_depth: 64,
            max_nodes: 10_000_000,
            max_result_bytes: 8 << 30,
        }
    }
}

/// Longest module or attribute name accepted in GLOBAL.
const MAX_GLOBAL_NAME_BYTES: usize = 256;

/// What went wrong, and where in the pickle.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("byte {offset}: {problem}")]
pub struct PickleError {
    /// Offset of the opcode being executed.
    pub offset: usize,
    pub problem: String,
}

/// A value read from a pickle. numpy scalars are 0-d [`Value::Array`]s.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    List(Vec<Value>),
    Tuple(Vec<Value>),
    /// Insertion order; a key set twice keeps its last value (as Python does).
    Dict(Vec<(Value, Value)>),
    Array(NdArray),
}

impl Value {
    /// The value stored under a string key, when `self` is a dict.
    pub fn get(&self, key: &str) -> Option<&Value> {
        match self {
            Value::Dict(items) => items
                .iter()
                .find(|(k, _)| matches!(k, Value::Str(s) if s == key))
                .map(|(_, v)| v),
            _ => None,
        }
    }

    /// What kind of value this is, for error messages.
    pub fn describe(&self) -> String {
        match self {
            Value::None => "None".into(),
            Value::Bool(_) => "bool".into(),
            Value::Int(_) => "int".into(),
            Value::Float(_) => "float".into(),
            Value::Str(_) => "str".into(),
            Value::Bytes(_) => "bytes".into(),
            Value::List(v) => format!("list of {}", v.len()),
            Value::Tuple(v) => format!("tuple of {}", v.len()),
            Value::Dict(v) => format!("dict of {}", v.len()),
            Value::Array(a) if a.shape().is_empty() => format!("numpy {} scalar", a.element()),
            Value::Array(a) => format!("numpy {}", a.describe()),
        }
    }
}

/// Reads a pickle with the default [`Limits`].
pub fn from_slice(bytes: &[u8]) -> Result<Value, PickleError> {
    from_slice_with_limits(bytes, &Limits::default())
}

/// Reads a pickle. The whole input must be one pickle (nothing after STOP).
pub fn from_slice_with_limits(bytes: &[u8], limits: &Limits) -> Result<Value, PickleError> {
    if bytes.len() > limits.max_input_bytes {
        return Err(PickleError {
            offset: 0,
            problem: format!(
                "pickle is {} bytes, more than the limit of {}",
                bytes.len(),
                limits.max_input_bytes
            ),
        });
    }
    let mut machine = Machine {
        input: bytes,
        pos: 0,
        op_start: 0,
        arena: Vec::new(),
        stack: Vec::new(),
        fences: Vec::new(),
        memo: HashMap::new(),
    };
    let root = machine.run()?;
    let mut budget = Budget {
        nodes_left: limits.max_nodes,
        bytes_left: limits.max_result_bytes,
        max_depth: limits.max_depth,
    };
    machine.to_value(root, 0, &mut budget)
}

/// The only callables a pickle may reference.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Callable {
    /// `numpy.core.multiarray._reconstruct` (numpy 1) / `numpy._core.multiarray._reconstruct` (numpy 2).
    Reconstruct,
    /// `numpy.ndarray`, only as `_reconstruct`'s first argument.
    NdarrayClass,
    /// `numpy.dtype`.
    DTypeClass,
    /// `numpy.core.multiarray.scalar`: a numpy scalar from dtype and raw bytes.
    Scalar,
    /// `numpy.core.numeric._frombuffer`: protocol 5 arrays.
    FromBuffer,
    /// `_codecs.encode`: protocol 2 spells bytes as `encode(latin1 str, 'latin1')`.
    CodecsEncode,
    /// `builtins.bytes` (`__builtin__.bytes` in protocol 2): Python bytes under protocol 2.
    BytesClass,
}

impl Callable {
    fn resolve(module: &str, name: &str) -> Option<Callable> {
        let numpy_core = |sub: &str| {
            module == format!("numpy.core.{sub}") || module == format!("numpy._core.{sub}")
        };
        Some(match name {
            "_reconstruct" if numpy_core("multiarray") => Callable::Reconstruct,
            "scalar" if numpy_core("multiarray") => Callable::Scalar,
            "_frombuffer" if numpy_core("numeric") => Callable::FromBuffer,
            "ndarray" if module == "numpy" => Callable::NdarrayClass,
            "dtype" if module == "numpy" => Callable::DTypeClass,
            "encode" if module == "_codecs" => Callable::CodecsEncode,
            "bytes" if module == "builtins" || module == "__builtin__" => Callable::BytesClass,
            _ => return None,
        })
    }
}

impl fmt::Display for Callable {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Callable::Reconstruct => "numpy _reconstruct",
            Callable::NdarrayClass => "numpy.ndarray",
            Callable::DTypeClass => "numpy.dtype",
            Callable::Scalar => "numpy scalar",
            Callable::FromBuffer => "numpy _frombuffer",
            Callable::CodecsEncode => "_codecs.encode",
            Callable::BytesClass => "bytes",
        })
    }
}

#[derive(Debug, Clone, Copy)]
struct DType {
    element: Element,
    order: ByteOrder,
}

type ObjId = usize;

/// Objects live in an arena so that the memo, the stack and containers share
/// them by index: BUILD and APPEND then mutate the one object every reference
/// sees, as in Python (numpy's dtype is memoised before its BUILD).
#[derive(Debug)]
enum Obj {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    List(Vec<ObjId>),
    Tuple(Vec<ObjId>),
    Dict(Vec<(ObjId, ObjId)>),
    Callable(Callable),
    DType(DType),
    /// `_reconstruct`'s result, waiting for its BUILD.
    PendingArray,
    Array(NdArray),
}

impl Obj {
    fn kind(&self) -> &'static str {
        match self {
            Obj::None => "None",
            Obj::Bool(_) => "bool",
            Obj::Int(_) => "int",
            Obj::Float(_) => "float",
            Obj::Str(_) => "str",
            Obj::Bytes(_) => "bytes",
            Obj::List(_) => "list",
            Obj::Tuple(_) => "tuple",
            Obj::Dict(_) => "dict",
            Obj::Callable(_) => "callable",
            Obj::DType(_) => "numpy.dtype",
            Obj::PendingArray => "numpy array without its state (BUILD missing)",
            Obj::Array(_) => "numpy array",
        }
    }
}

struct Machine<'a> {
    input: &'a [u8],
    pos: usize,
    op_start: usize,
    arena: Vec<Obj>,
    stack: Vec<ObjId>,
    /// Stack lengths at each MARK; nothing may be popped below the innermost.
    fences: Vec<usize>,
    memo: HashMap<u64, ObjId>,
}

struct Budget {
    nodes_left: usize,
    bytes_left: usize,
    max_depth: usize,
}

mod op {
    pub const MARK: u8 = b'(';
    pub const STOP: u8 = b'.';
    pub const POP: u8 = b'0';
    pub const POP_MARK: u8 = b'1';
    pub const DUP: u8 = b'2';
    pub const BININT: u8 = b'J';
    pub const BININT1: u8 = b'K';
    pub const BININT2: u8 = b'M';
    pub const NONE: u8 = b'N';
    pub const BINFLOAT: u8 = b'G';
    pub const SHORT_BINSTRING: u8 = b'U';
    pub const BINSTRING: u8 = b'T';
    pub const BINUNICODE: u8 = b'X';
    pub const APPEND: u8 = b'a';
    pub const BUILD: u8 = b'b';
    pub const GLOBAL: u8 = b'c';
    pub const DICT: u8 = b'd';
    pub const EMPTY_DICT: u8 = b'}';
    pub const APPENDS: u8 = b'e';
    pub const BINGET: u8 = b'h';
    pub const LONG_BINGET: u8 = b'j';
    pub const LIST: u8 = b'l';
    pub const EMPTY_LIST: u8 = b']';
    pub const BINPUT: u8 = b'q';
    pub const LONG_BINPUT: u8 = b'r';
    pub const REDUCE: u8 = b'R';
    pub const SETITEM: u8 = b's';
    pub const TUPLE: u8 = b't';
    pub const EMPTY_TUPLE: u8 = b')';
    pub const SETITEMS: u8 = b'u';
    pub const PROTO: u8 = 0x80;
    pub const NEWOBJ: u8 = 0x81;
    pub const TUPLE1: u8 = 0x85;
    pub const TUPLE2: u8 = 0x86;
    pub const TUPLE3: u8 = 0x87;
    pub const NEWTRUE: u8 = 0x88;
    pub const NEWFALSE: u8 = 0x89;
    pub const LONG1: u8 = 0x8a;
    pub const LONG4: u8 = 0x8b;
    pub const SHORT_BINBYTES: u8 = b'C';
    pub const BINBYTES: u8 = b'B';
    pub const SHORT_BINUNICODE: u8 = 0x8c;
    pub const BINUNICODE8: u8 = 0x8d;
    pub const BINBYTES8: u8 = 0x8e;
    pub const NEWOBJ_EX: u8 = 0x92;
    pub const STACK_GLOBAL: u8 = 0x93;
    pub const MEMOIZE: u8 = 0x94;
    pub const FRAME: u8 = 0x95;
    pub const BYTEARRAY8: u8 = 0x96;
    pub const NEXT_BUFFER: u8 = 0x97;
    pub const READONLY_BUFFER: u8 = 0x98;
}

/// Highest pickle protocol understood.
const MAX_PROTOCOL: u8 = 5;

impl Machine<'_> {
    fn error(&self, problem: impl Into<String>) -> PickleError {
        PickleError {
            offset: self.op_start,
            problem: problem.into(),
        }
    }

    fn take(&mut self, n: usize) -> Result<&[u8], PickleError> {
        let remaining = self.input.len() - self.pos;
        if n > remaining {
            return Err(self.error(format!(
                "truncated: needs {n} more bytes, only {remaining} left"
            )));
        }
        let start = self.pos;
        self.pos += n;
        Ok(&self.input[start..start + n])
    }

    fn take_array<const N: usize>(&mut self) -> Result<[u8; N], PickleError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    fn take_u8(&mut self) -> Result<u8, PickleError> {
        Ok(self.take_array::<1>()?[0])
    }

    /// A length field: it must fit in the remaining input before anything is allocated.
    fn take_len(&mut self, width: usize) -> Result<usize, PickleError> {
        let value = match width {
            1 => u64::from(self.take_u8()?),
            4 => u64::from(u32::from_le_bytes(self.take_array()?)),
            _ => u64::from_le_bytes(self.take_array()?),
        };
        let remaining = self.input.len() - self.pos;
        match usize::try_from(value) {
            Ok(len) if len <= remaining => Ok(len),
            _ => Err(self.error(format!(
                "truncated or corrupt: length field says {value} bytes, only {remaining} left"
            ))),
        }
    }

    fn take_line(&mut self) -> Result<String, PickleError> {
        let rest = &self.input[self.pos..];
        let window = &rest[..rest.len().min(MAX_GLOBAL_NAME_BYTES + 1)];
        let Some(end) = window.iter().position(|&b| b == b'\n') else {
            return Err(self.error(format!(
                "GLOBAL name not terminated by a newline within {MAX_GLOBAL_NAME_BYTES} bytes"
            )));
        };
        let line = std::str::from_utf8(&window[..end])
            .map_err(|_| self.error("GLOBAL name is not UTF-8"))?
            .to_owned();
        self.pos += end + 1;
        Ok(line)
    }

    fn take_utf8(&mut self, len: usize) -> Result<String, PickleError> {
        let bytes = self.take(len)?;
        match std::str::from_utf8(bytes) {
            Ok(s) => Ok(s.to_owned()),
            Err(e) => Err(self.error(format!("string is not valid UTF-8: {e}"))),
        }
    }

    fn alloc(&mut self, obj: Obj) -> ObjId {
        self.arena.push(obj);
        self.arena.len() - 1
    }

    fn push(&mut self, obj: Obj) {
        let id = self.alloc(obj);
        self.stack.push(id);
    }

    fn fence(&self) -> usize {
        self.fences.last().copied().unwrap_or(0)
    }

    fn pop(&mut self) -> Result<ObjId, PickleError> {
        if self.stack.len() <= self.fence() {
            return Err(self.error("stack underflow"));
        }
        self.stack
            .pop()
            .ok_or_else(|| self.error("stack underflow"))
    }

    fn top(&self) -> Result<ObjId, PickleError> {
        if self.stack.len() <= self.fence() {
            return Err(self.error("stack underflow (no object to work on)"));
        }
        self.stack
            .last()
            .copied()
            .ok_or_else(|| self.error("stack underflow"))
    }

    /// Pops everything above the innermost MARK, and the MARK.
    fn pop_mark(&mut self) -> Result<Vec<ObjId>, PickleError> {
        let Some(fence) = self.fences.pop() else {
            return Err(self.error("MARK expected but none is open"));
        };
        Ok(self.stack.split_off(fence.min(self.stack.len())))
    }

    fn memo_put(&mut self, key: u64) -> Result<(), PickleError> {
        let top = self.top()?;
        self.memo.insert(key, top);
        Ok(())
    }

    fn memo_get(&mut self, key: u64) -> Result<(), PickleError> {
        let Some(&id) = self.memo.get(&key) else {
            return Err(self.error(format!("memo entry {key} was never stored")));
        };
        self.stack.push(id);
        Ok(())
    }

    fn run(&mut self) -> Result<ObjId, PickleError> {
        loop {
            self.op_start = self.pos;
            let opcode = self.take_u8()?;
            match opcode {
                op::PROTO => {
                    let version = self.take_u8()?;
                    if version > MAX_PROTOCOL {
                        return Err(self.error(format!(
                            "pickle protocol {version} is not supported (at most {MAX_PROTOCOL})"
                        )));
                    }
                }
                op::FRAME => {
                    // Frames only group opcodes for buffering; the length must still be plausible.
                    self.take_len(8)?;
                }
                op::STOP => {
                    let result = self.pop()?;
                    if self.pos != self.input.len() {
                        return Err(self.error(format!(
                            "{} unexpected bytes after the end of the pickle",
                            self.input.len() - self.pos
                        )));
                    }
                    return Ok(result);
                }
                op::MARK => self.fences.push(self.stack.len()),
                op::POP => {
                    self.pop()?;
                }
                op::POP_MARK => {
                    self.pop_mark()?;
                }
                op::DUP => {
                    let top = self.top()?;
                    self.stack.push(top);
                }
                op::NONE => self.push(Obj::None),
                op::NEWTRUE => self.push(Obj::Bool(true)),
                op::NEWFALSE => self.push(Obj::Bool(false)),
                op::BININT => {
                    let v = i32::from_le_bytes(self.take_array()?);
                    self.push(Obj::Int(i64::from(v)));
                }
                op::BININT1 => {
                    let v = self.take_u8()?;
                    self.push(Obj::Int(i64::from(v)));
                }
                op::BININT2 => {
                    let v = u16::from_le_bytes(self.take_array()?);
                    self.push(Obj::Int(i64::from(v)));
                }
                op::LONG1 | op::LONG4 => {
                    let len = self.take_len(if opcode == op::LONG1 { 1 } else { 4 })?;
                    let bytes = self.take(len)?.to_vec();
                    let v = self.long_from_bytes(&bytes)?;
                    self.push(Obj::Int(v));
                }
                op::BINFLOAT => {
                    let v = f64::from_be_bytes(self.take_array()?);
                    self.push(Obj::Float(v));
                }
                op::SHORT_BINUNICODE | op::BINUNICODE | op::BINUNICODE8 => {
                    let width = match opcode {
                        op::SHORT_BINUNICODE => 1,
                        op::BINUNICODE => 4,
                        _ => 8,
                    };
                    let len = self.take_len(width)?;
                    let s = self.take_utf8(len)?;
                    self.push(Obj::Str(s));
                }
                // Python 2 `str` (SHORT_BINSTRING, BINSTRING) is raw bytes, as numpy's array data was.
                op::SHORT_BINBYTES
                | op::BINBYTES
                | op::BINBYTES8
                | op::BYTEARRAY8
                | op::SHORT_BINSTRING
                | op::BINSTRING => {
                    let width = match opcode {
                        op::SHORT_BINBYTES | op::SHORT_BINSTRING => 1,
                        op::BINBYTES | op::BINSTRING => 4,
                        _ => 8,
                    };
                    let len = self.take_len(width)?;
                    let bytes = self.take(len)?.to_vec();
                    self.push(Obj::Bytes(bytes));
                }
                op::EMPTY_DICT => self.push(Obj::Dict(Vec::new())),
                op::EMPTY_LIST => self.push(Obj::List(Vec::new())),
                op::EMPTY_TUPLE => self.push(Obj::Tuple(Vec::new())),
                op::TUPLE1 | op::TUPLE2 | op::TUPLE3 => {
                    let n = usize::from(opcode - op::TUPLE1) + 1;
                    let mut items = vec![0; n];
                    for slot in items.iter_mut().rev() {
                        *slot = self.pop()?;
                    }
                    self.push(Obj::Tuple(items));
                }
                op::TUPLE => {
                    let items = self.pop_mark()?;
                    self.push(Obj::Tuple(items));
                }
                op::LIST => {
                    let items = self.pop_mark()?;
                    self.push(Obj::List(items));
                }
                op::DICT => {
                    let items = self.pop_mark()?;
                    let pairs = self.pairs(items)?;
                    self.push(Obj::Dict(pairs));
                }
                op::APPEND => {
                    let item = self.pop()?;
                    self.extend_list(vec![item])?;
                }
                op::APPENDS => {
                    let items = self.pop_mark()?;
                    self.extend_list(items)?;
                }
                op::SETITEM => {
                    let value = self.pop()?;
                    let key = self.pop()?;
                    self.extend_dict(vec![(key, value)])?;
                }
                op::SETITEMS => {
                    let items = self.pop_mark()?;
                    let pairs = self.pairs(items)?;
                    self.extend_dict(pairs)?;
                }
                op::MEMOIZE => {
                    let key = self.memo.len() as u64;
                    self.memo_put(key)?;
                }
                op::BINPUT => {
                    let key = self.take_u8()?;
                    self.memo_put(u64::from(key))?;
                }
                op::LONG_BINPUT => {
                    let key = u32::from_le_bytes(self.take_array()?);
                    self.memo_put(u64::from(key))?;
                }
                op::BINGET => {
                    let key = self.take_u8()?;
                    self.memo_get(u64::from(key))?;
                }
                op::LONG_BINGET => {
                    let key = u32::from_le_bytes(self.take_array()?);
                    self.memo_get(u64::from(key))?;
                }
                op::GLOBAL => {
                    let module = self.take_line()?;
                    let name = self.take_line()?;
                    self.push_global(&module, &name)?;
                }
                op::STACK_GLOBAL => {
                    let name_id = self.pop()?;
                    let module_id = self.pop()?;
                    let (Obj::Str(module), Obj::Str(name)) =
                        (&self.arena[module_id], &self.arena[name_id])
                    else {
                        return Err(self.error("STACK_GLOBAL needs two strings"));
                    };
                    let (module, name) = (module.clone(), name.clone());
                    self.push_global(&module, &name)?;
                }
                op::REDUCE | op::NEWOBJ => {
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    let result = self.call(callable, args)?;
                    self.push(result);
                }
                op::NEWOBJ_EX => {
                    let kwargs = self.pop()?;
                    if !matches!(&self.arena[kwargs], Obj::Dict(d) if d.is_empty()) {
                        return Err(self.error("NEWOBJ_EX with keyword arguments is not supported"));
                    }
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    let result = self.call(callable, args)?;
                    self.push(result);
                }
                op::BUILD => {
                    let state = self.pop()?;
                    let target = self.top()?;
                    self.build(target, state)?;
                }
                op::READONLY_BUFFER => {
                    self.top()?;
                }
                op::NEXT_BUFFER => {
                    return Err(self.error(
                        "out-of-band buffers (pickle protocol 5 buffer_callback) are not supported",
                    ));
                }
                other => {
                    return Err(self.error(format!(
                        "opcode 0x{other:02x} is not supported (only what pickle.dump emits for \
                         dicts, lists, tuples, scalars, strings and numpy arrays)"
                    )));
                }
            }
        }
    }

    fn long_from_bytes(&self, bytes: &[u8]) -> Result<i64, PickleError> {
        // Little-endian two's complement; longer encodings are fine if they sign-extend an i64.
        let negative = bytes.last().is_some_and(|&b| b & 0x80 != 0);
        let fill = if negative { 0xff } else { 0x00 };
        let mut buf = [fill; 8];
        if bytes.len() > 8 {
            let (low, high) = bytes.split_at(8);
            let sign_ok = (low[7] & 0x80 != 0) == negative;
            if !sign_ok || high.iter().any(|&b| b != fill) {
                return Err(self.error("integer does not fit in 64 bits"));
            }
            buf.copy_from_slice(low);
        } else {
            buf[..bytes.len()].copy_from_slice(bytes);
        }
        Ok(i64::from_le_bytes(buf))
    }

    fn pairs(&self, items: Vec<ObjId>) -> Result<Vec<(ObjId, ObjId)>, PickleError> {
        if !items.len().is_multiple_of(2) {
            return Err(self.error("odd number of items for a dict"));
        }
        Ok(items.chunks_exact(2).map(|kv| (kv[0], kv[1])).collect())
    }

    fn extend_list(&mut self, items: Vec<ObjId>) -> Result<(), PickleError> {
        let target = self.top()?;
        match &mut self.arena[target] {
            Obj::List(list) => {
                list.extend(items);
                Ok(())
            }
            other => {
                let kind = other.kind();
                Err(self.error(format!("APPEND to a {kind}, not a list")))
            }
        }
    }

    fn extend_dict(&mut self, pairs: Vec<(ObjId, ObjId)>) -> Result<(), PickleError> {
        let target = self.top()?;
        match &mut self.arena[target] {
            Obj::Dict(dict) => {
                dict.extend(pairs);
                Ok(())
            }
            other => {
                let kind = other.kind();
                Err(self.error(format!("SETITEM on a {kind}, not a dict")))
            }
        }
    }

    fn push_global(&mut self, module: &str, name: &str) -> Result<(), PickleError> {
        match Callable::resolve(module, name) {
            Some(callable) => {
                self.push(Obj::Callable(callable));
                Ok(())
            }
            None => Err(self.error(format!(
                "global {module}.{name} is not allowed (only numpy arrays, dtypes and scalars are read)"
            ))),
        }
    }

    fn tuple_items(&self, id: ObjId, what: &str) -> Result<Vec<ObjId>, PickleError> {
        match &self.arena[id] {
            Obj::Tuple(items) => Ok(items.clone()),
            other => Err(self.error(format!("{what} must be a tuple, found {}", other.kind()))),
        }
    }

    fn str_of(&self, id: ObjId, what: &str) -> Result<String, PickleError> {
        match &self.arena[id] {
            Obj::Str(s) => Ok(s.clone()),
            other => Err(self.error(format!("{what} must be a str, found {}", other.kind()))),
        }
    }

    fn bytes_of(&self, id: ObjId, what: &str) -> Result<&[u8], PickleError> {
        match &self.arena[id] {
            Obj::Bytes(b) => Ok(b),
            other => Err(self.error(format!("{what} must be bytes, found {}", other.kind()))),
        }
    }

    fn bool_of(&self, id: ObjId, what: &str) -> Result<bool, PickleError> {
        match &self.arena[id] {
            Obj::Bool(b) => Ok(*b),
            Obj::Int(0) => Ok(false),
            Obj::Int(1) => Ok(true),
            other => Err(self.error(format!("{what} must be a bool, found {}", other.kind()))),
        }
    }

    fn dtype_of(&self, id: ObjId, what: &str) -> Result<DType, PickleError> {
        match &self.arena[id] {
            Obj::DType(d) => Ok(*d),
            other => Err(self.error(format!(
                "{what} must be a numpy.dtype, found {}",
                other.kind()
            ))),
        }
    }

    fn shape_of(&self, id: ObjId, what: &str) -> Result<Vec<usize>, PickleError> {
        let items = match &self.arena[id] {
            Obj::Tuple(items) | Obj::List(items) => items.clone(),
            // `_frombuffer` of a 1-d array may carry a bare int.
            Obj::Int(_) => vec![id],
            other => {
                return Err(self.error(format!(
                    "{what} must be a tuple of ints, found {}",
                    other.kind()
                )));
            }
        };
        items
            .iter()
            .map(|&item| match &self.arena[item] {
                Obj::Int(v) => usize::try_from(*v)
                    .map_err(|_| self.error(format!("{what} has a negative dimension {v}"))),
                other => Err(self.error(format!("{what} must hold ints, found {}", other.kind()))),
            })
            .collect()
    }

    fn call(&mut self, callable_id: ObjId, args_id: ObjId) -> Result<Obj, PickleError> {
        let Obj::Callable(callable) = self.arena[callable_id] else {
            let kind = self.arena[callable_id].kind();
            return Err(self.error(format!("REDUCE on a {kind}, which cannot be called")));
        };
        let args = self.tuple_items(args_id, &format!("arguments of {callable}"))?;
        let arity = |range: std::ops::RangeInclusive<usize>| {
            if range.contains(&args.len()) {
                Ok(())
            } else {
                Err(self.error(format!(
                    "{callable} takes {} to {} arguments, got {}",
                    range.start(),
                    range.end(),
                    args.len()
                )))
            }
        };
        match callable {
            Callable::Reconstruct => {
                arity(3..=3)?;
                if !matches!(self.arena[args[0]], Obj::Callable(Callable::NdarrayClass)) {
                    return Err(self.error(
                        "_reconstruct builds only numpy.ndarray (subclasses are not supported)",
                    ));
                }
                Ok(Obj::PendingArray)
            }
            Callable::DTypeClass => {
                arity(1..=3)?;
                let spec = self.str_of(args[0], "numpy.dtype's type code")?;
                let Some((element, order)) = parse_descriptor(&spec) else {
                    return Err(self.error(format!(
                        "numpy dtype '{spec}' is not supported (bool, int8-64, uint8-64, float32, float64 are)"
                    )));
                };
                Ok(Obj::DType(DType { element, order }))
            }
            Callable::Scalar => {
                arity(2..=2)?;
                let dtype = self.dtype_of(args[0], "scalar's dtype")?;
                let raw = self.bytes_of(args[1], "scalar's data")?;
                NdArray::from_raw(dtype.element, dtype.order, Vec::new(), false, raw)
                    .map(Obj::Array)
                    .map_err(|e| self.error(format!("numpy scalar: {e}")))
            }
            Callable::FromBuffer => {
                arity(4..=4)?;
                let dtype = self.dtype_of(args[1], "_frombuffer's dtype")?;
                let shape = self.shape_of(args[2], "_frombuffer's shape")?;
                let order = self.str_of(args[3], "_frombuffer's order")?;
                let fortran = match order.as_str() {
                    "C" => false,
                    "F" => true,
                    other => {
                        return Err(self.error(format!(
                            "_frombuffer's order must be 'C' or 'F', found '{other}'"
                        )));
                    }
                };
                let raw = self.bytes_of(args[0], "_frombuffer's buffer")?;
                NdArray::from_raw(dtype.element, dtype.order, shape, fortran, raw)
                    .map(Obj::Array)
                    .map_err(|e| self.error(format!("numpy array: {e}")))
            }
            Callable::CodecsEncode => {
                arity(2..=2)?;
                let text = self.str_of(args[0], "_codecs.encode's text")?;
                let encoding = self.str_of(args[1], "_codecs.encode's encoding")?;
                if !matches!(
                    encoding.to_ascii_lowercase().as_str(),
                    "latin1" | "latin-1" | "iso-8859-1"
                ) {
                    return Err(self.error(format!(
                        "_codecs.encode with encoding '{encoding}' is not supported (only latin1)"
                    )));
                }
                text.chars()
                    .map(|c| u8::try_from(u32::from(c)).ok())
                    .collect::<Option<Vec<u8>>>()
                    .map(Obj::Bytes)
                    .ok_or_else(|| self.error("_codecs.encode: text is not latin1"))
            }
            Callable::BytesClass => {
                arity(0..=1)?;
                match args.first() {
                    None => Ok(Obj::Bytes(Vec::new())),
                    Some(&arg) => Ok(Obj::Bytes(self.bytes_of(arg, "bytes' argument")?.to_vec())),
                }
            }
            Callable::NdarrayClass => {
                Err(self.error("numpy.ndarray is only supported as _reconstruct's argument"))
            }
        }
    }

    fn build(&mut self, target: ObjId, state_id: ObjId) -> Result<(), PickleError> {
        match self.arena[target] {
            Obj::PendingArray => {
                let state = self.tuple_items(state_id, "numpy array state")?;
                // (version, shape, dtype, is_fortran, data); old numpy omits the version.
                let fields = match state.len() {
                    5 => &state[1..],
                    4 => &state[..],
                    n => {
                        return Err(self.error(format!(
                            "numpy array state must have 4 or 5 items, found {n}"
                        )));
                    }
                };
                let shape = self.shape_of(fields[0], "numpy array shape")?;
                let dtype = self.dtype_of(fields[1], "numpy array dtype")?;
                let fortran = self.bool_of(fields[2], "numpy array is_fortran flag")?;
                if matches!(self.arena[fields[3]], Obj::List(_)) {
                    return Err(self.error("numpy object arrays are not supported"));
                }
                let raw = self.bytes_of(fields[3], "numpy array data")?;
                let array = NdArray::from_raw(dtype.element, dtype.order, shape, fortran, raw)
                    .map_err(|e| self.error(format!("numpy array: {e}")))?;
                self.arena[target] = Obj::Array(array);
                Ok(())
            }
            Obj::DType(dtype) => {
                // (version, byteorder, subarray, names, fields, elsize, alignment, flags[, metadata])
                let state = self.tuple_items(state_id, "numpy dtype state")?;
                if state.len() < 5 {
                    return Err(self.error(format!(
                        "numpy dtype state must have at least 5 items, found {}",
                        state.len()
                    )));
                }
                let order_text = self.str_of(state[1], "numpy dtype byte order")?;
                let mut chars = order_text.chars();
                let order = match (chars.next(), chars.next()) {
                    (Some(c), None) => ByteOrder::from_numpy_char(c),
                    _ => None,
                }
                .ok_or_else(|| {
                    self.error(format!(
                        "numpy dtype byte order '{order_text}' is not valid"
                    ))
                })?;
                if state[2..5]
                    .iter()
                    .any(|&id| !matches!(self.arena[id], Obj::None))
                {
                    return Err(
                        self.error("structured or sub-array numpy dtypes are not supported")
                    );
                }
                self.arena[target] = Obj::DType(DType {
                    element: dtype.element,
                    order,
                });
                Ok(())
            }
            ref other => Err(self.error(format!(
                "BUILD on a {} is not supported (only numpy arrays and dtypes)",
                other.kind()
            ))),
        }
    }

    /// Expands the arena object `id` into an owned value within `budget`.
    fn to_value(&self, id: ObjId, depth: usize, budget: &mut Budget) -> Result<Value, PickleError> {
        let over = |what: &str| PickleError {
            offset: self.input.len(),
            problem: format!("result exceeds the limit on {what}"),
        };
        if depth > budget.max_depth {
            return Err(over("nesting depth (or the pickle is recursive)"));
        }
        budget.nodes_left = budget
            .nodes_left
            .checked_sub(1)
            .ok_or_else(|| over("values"))?;
        let mut charge = |n: usize| {
            budget.bytes_left = budget
                .bytes_left
                .checked_sub(n)
                .ok_or_else(|| over("bytes"))?;
            Ok::<(), PickleError>(())
        };
        Ok(match &self.arena[id] {
            Obj::None => Value::None,
            Obj::Bool(b) => Value::Bool(*b),
            Obj::Int(v) => Value::Int(*v),
            Obj::Float(v) => Value::Float(*v),
            Obj::Str(s) => {
                charge(s.len())?;
                Value::Str(s.clone())
            }
            Obj::Bytes(b) => {
                charge(b.len())?;
                Value::Bytes(b.clone())
            }
            Obj::Array(a) => {
                charge(a.byte_size())?;
                Value::Array(a.clone())
            }
            Obj::List(items) => Value::List(self.values(items, depth, budget)?),
            Obj::Tuple(items) => Value::Tuple(self.values(items, depth, budget)?),
            Obj::Dict(pairs) => {
                let mut out: Vec<(Value, Value)> = Vec::with_capacity(pairs.len());
                // A key set twice keeps its last value; only str and int keys
                // (all these files use) are compared, in constant time each.
                let mut index_of: HashMap<DictKey, usize> = HashMap::new();
                for &(k, v) in pairs {
                    let key = self.to_value(k, depth + 1, budget)?;
                    let value = self.to_value(v, depth + 1, budget)?;
                    let hashable = match &key {
                        Value::Str(s) => Some(DictKey::Str(s.clone())),
                        Value::Int(i) => Some(DictKey::Int(*i)),
                        _ => None,
                    };
                    match hashable.as_ref().and_then(|h| index_of.get(h)) {
                        Some(&slot) => out[slot].1 = value,
                        None => {
                            if let Some(h) = hashable {
                                index_of.insert(h, out.len());
                            }
                            out.push((key, value));
                        }
                    }
                }
                Value::Dict(out)
            }
            other @ (Obj::Callable(_) | Obj::DType(_) | Obj::PendingArray) => {
                return Err(PickleError {
                    offset: self.input.len(),
                    problem: format!("a {} cannot be part of the result", other.kind()),
                });
            }
        })
    }

    fn values(
        &self,
        items: &[ObjId],
        depth: usize,
        budget: &mut Budget,
    ) -> Result<Vec<Value>, PickleError> {
        items
            .iter()
            .map(|&item| self.to_value(item, depth + 1, budget))
            .collect()
    }
}

#[derive(Debug, PartialEq, Eq, Hash)]
enum DictKey {
    Str(String),
    Int(i64),
}
