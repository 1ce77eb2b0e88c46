//! numpy arrays decoded from raw bytes: the element types PhysTwin files use,
//! both byte orders, C and Fortran order. Shared by the unpickler and the
//! depth `.npy` reader so both accept exactly the same dtypes.

use std::fmt;

/// A numpy element type this crate can decode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Element {
    Bool,
    U8,
    U16,
    U32,
    U64,
    I8,
    I16,
    I32,
    I64,
    F32,
    F64,
}

impl Element {
    /// Parses a numpy type code without byte-order prefix (`f4`, `b1`, `u2`, ...).
    pub fn from_type_code(code: &str) -> Option<Element> {
        Some(match code {
            "b1" | "?" => Element::Bool,
            "u1" | "B" => Element::U8,
            "u2" | "H" => Element::U16,
            "u4" | "I" => Element::U32,
            "u8" | "L" | "Q" => Element::U64,
            "i1" | "b" => Element::I8,
            "i2" | "h" => Element::I16,
            "i4" | "i" => Element::I32,
            "i8" | "l" | "q" => Element::I64,
            "f4" | "f" => Element::F32,
            "f8" | "d" => Element::F64,
            _ => return None,
        })
    }

    pub fn item_size(self) -> usize {
        match self {
            Element::Bool | Element::U8 | Element::I8 => 1,
            Element::U16 | Element::I16 => 2,
            Element::U32 | Element::I32 | Element::F32 => 4,
            Element::U64 | Element::I64 | Element::F64 => 8,
        }
    }

    /// numpy's name for the type.
    pub fn name(self) -> &'static str {
        match self {
            Element::Bool => "bool",
            Element::U8 => "uint8",
            Element::U16 => "uint16",
            Element::U32 => "uint32",
            Element::U64 => "uint64",
            Element::I8 => "int8",
            Element::I16 => "int16",
            Element::I32 => "int32",
            Element::I64 => "int64",
            Element::F32 => "float32",
            Element::F64 => "float64",
        }
    }

    pub fn is_float(self) -> bool {
        matches!(self, Element::F32 | Element::F64)
    }

    pub fn is_integer(self) -> bool {
        !self.is_float() && self != Element::Bool
    }
}

impl fmt::Display for Element {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Byte order of multi-byte elements as stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ByteOrder {
    Little,
    Big,
}

impl ByteOrder {
    /// numpy's byte-order character: `<`, `>`, `|` (not applicable) or `=`
    /// (native). Native is taken as little-endian: every platform numpy
    /// writes these files on is, and numpy pickles state it explicitly anyway.
    pub fn from_numpy_char(c: char) -> Option<ByteOrder> {
        match c {
            '<' | '|' | '=' => Some(ByteOrder::Little),
            '>' => Some(ByteOrder::Big),
            _ => None,
        }
    }
}

/// Parses a full numpy descriptor such as `<f4`, `|b1`, `>u2` or `f8`.
pub fn parse_descriptor(descr: &str) -> Option<(Element, ByteOrder)> {
    let mut chars = descr.chars();
    match chars.next() {
        Some(c @ ('<' | '>' | '|' | '=')) => {
            let order = ByteOrder::from_numpy_char(c)?;
            Some((Element::from_type_code(chars.as_str())?, order))
        }
        Some(_) => Some((Element::from_type_code(descr)?, ByteOrder::Little)),
        None => None,
    }
}

/// Element storage in C (row-major) order.
#[derive(Debug, Clone, PartialEq)]
pub enum ArrayData {
    Bool(Vec<bool>),
    U8(Vec<u8>),
    U16(Vec<u16>),
    U32(Vec<u32>),
    U64(Vec<u64>),
    I8(Vec<i8>),
    I16(Vec<i16>),
    I32(Vec<i32>),
    I64(Vec<i64>),
    F32(Vec<f32>),
    F64(Vec<f64>),
}

/// A decoded numpy array (or 0-d numpy scalar), always stored in C order.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray {
    shape: Vec<usize>,
    data: ArrayData,
}

/// Formats a shape like numpy does: `(5, 7, 3)`, `(4,)`, `()`.
pub fn shape_string(shape: &[usize]) -> String {
    dm_bundle::shape_string(shape)
}

/// Number of elements of `shape`, `None` on overflow.
pub fn element_count(shape: &[usize]) -> Option<usize> {
    shape.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d))
}

impl NdArray {
    /// Decodes `raw`, which must hold exactly the bytes `shape` needs.
    /// The error is a sentence for a message naming the file and field.
    pub fn from_raw(
        element: Element,
        order: ByteOrder,
        shape: Vec<usize>,
        fortran_order: bool,
        raw: &[u8],
    ) -> Result<NdArray, String> {
        let expected = element_count(&shape)
            .and_then(|n| n.checked_mul(element.item_size()))
            .ok_or_else(|| format!("shape {} is too large", shape_string(&shape)))?;
        if raw.len() != expected {
            return Err(format!(
                "{} array of shape {} needs {expected} data bytes, found {}",
                element,
                shape_string(&shape),
                raw.len()
            ));
        }
        let big = order == ByteOrder::Big;
        let data = match element {
            Element::Bool => ArrayData::Bool(raw.iter().map(|&b| b != 0).collect()),
            Element::U8 => ArrayData::U8(raw.to_vec()),
            Element::I8 => ArrayData::I8(raw.iter().map(|&b| b as i8).collect()),
            Element::U16 => {
                ArrayData::U16(decode(raw, big, u16::from_le_bytes, u16::from_be_bytes))
            }
            Element::U32 => {
                ArrayData::U32(decode(raw, big, u32::from_le_bytes, u32::from_be_bytes))
            }
            Element::U64 => {
                ArrayData::U64(decode(raw, big, u64::from_le_bytes, u64::from_be_bytes))
            }
            Element::I16 => {
                ArrayData::I16(decode(raw, big, i16::from_le_bytes, i16::from_be_bytes))
            }
            Element::I32 => {
                ArrayData::I32(decode(raw, big, i32::from_le_bytes, i32::from_be_bytes))
            }
            Element::I64 => {
                ArrayData::I64(decode(raw, big, i64::from_le_bytes, i64::from_be_bytes))
            }
            Element::F32 => {
                ArrayData::F32(decode(raw, big, f32::from_le_bytes, f32::from_be_bytes))
            }
            Element::F64 => {
                ArrayData::F64(decode(raw, big, f64::from_le_bytes, f64::from_be_bytes))
            }
        };
        let mut array = NdArray { shape, data };
        if fortran_order && array.shape.len() > 1 {
            array.data = array.data.fortran_to_c(&array.shape);
        }
        Ok(array)
    }

    pub fn shape(&self) -> &[usize] {
        &self.shape
    }

    pub fn data(&self) -> &ArrayData {
        &self.data
    }

    pub fn element(&self) -> Element {
        match &self.data {
            ArrayData::Bool(_) => Element::Bool,
            ArrayData::U8(_) => Element::U8,
            ArrayData::U16(_) => Element::U16,
            ArrayData::U32(_) => Element::U32,
            ArrayData::U64(_) => Element::U64,
            ArrayData::I8(_) => Element::I8,
            ArrayData::I16(_) => Element::I16,
            ArrayData::I32(_) => Element::I32,
            ArrayData::I64(_) => Element::I64,
            ArrayData::F32(_) => Element::F32,
            ArrayData::F64(_) => Element::F64,
        }
    }

    /// Number of elements (1 for a 0-d scalar).
    pub fn len(&self) -> usize {
        self.data.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Size in bytes as decoded, for memory limits.
    pub fn byte_size(&self) -> usize {
        self.len().saturating_mul(self.element().item_size())
    }

    /// Every element as f64, for numeric (non-bool) arrays. 64-bit integers
    /// beyond 2^53 lose precision, which no coordinate or pixel value reaches.
    pub fn to_f64_vec(&self) -> Option<Vec<f64>> {
        fn cast<T: Copy>(v: &[T], f: impl Fn(T) -> f64) -> Vec<f64> {
            v.iter().map(|&x| f(x)).collect()
        }
        Some(match &self.data {
            ArrayData::Bool(_) => return None,
            ArrayData::U8(v) => cast(v, f64::from),
            ArrayData::U16(v) => cast(v, f64::from),
            ArrayData::U32(v) => cast(v, f64::from),
            ArrayData::U64(v) => cast(v, |x| x as f64),
            ArrayData::I8(v) => cast(v, f64::from),
            ArrayData::I16(v) => cast(v, f64::from),
            ArrayData::I32(v) => cast(v, f64::from),
            ArrayData::I64(v) => cast(v, |x| x as f64),
            ArrayData::F32(v) => cast(v, f64::from),
            ArrayData::F64(v) => v.clone(),
        })
    }

    pub fn as_bools(&self) -> Option<&[bool]> {
        match &self.data {
            ArrayData::Bool(v) => Some(v),
            _ => None,
        }
    }

    /// `float32 (2, 3)`, for messages.
    pub fn describe(&self) -> String {
        format!(
            "{} array of shape {}",
            self.element(),
            shape_string(&self.shape)
        )
    }
}

impl ArrayData {
    pub fn len(&self) -> usize {
        match self {
            ArrayData::Bool(v) => v.len(),
            ArrayData::U8(v) => v.len(),
            ArrayData::U16(v) => v.len(),
            ArrayData::U32(v) => v.len(),
            ArrayData::U64(v) => v.len(),
            ArrayData::I8(v) => v.len(),
            ArrayData::I16(v) => v.len(),
            ArrayData::I32(v) => v.len(),
            ArrayData::I64(v) => v.len(),
            ArrayData::F32(v) => v.len(),
            ArrayData::F64(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn fortran_to_c(self, shape: &[usize]) -> ArrayData {
        match self {
            ArrayData::Bool(v) => ArrayData::Bool(fortran_to_c(&v, shape)),
            ArrayData::U8(v) => ArrayData::U8(fortran_to_c(&v, shape)),
            ArrayData::U16(v) => ArrayData::U16(fortran_to_c(&v, shape)),
            ArrayData::U32(v) => ArrayData::U32(fortran_to_c(&v, shape)),
            ArrayData::U64(v) => ArrayData::U64(fortran_to_c(&v, shape)),
            ArrayData::I8(v) => ArrayData::I8(fortran_to_c(&v, shape)),
            ArrayData::I16(v) => ArrayData::I16(fortran_to_c(&v, shape)),
            ArrayData::I32(v) => ArrayData::I32(fortran_to_c(&v, shape)),
            ArrayData::I64(v) => ArrayData::I64(fortran_to_c(&v, shape)),
            ArrayData::F32(v) => ArrayData::F32(fortran_to_c(&v, shape)),
            ArrayData::F64(v) => ArrayData::F64(fortran_to_c(&v, shape)),
        }
    }
}

fn decode<T, const N: usize>(
    raw: &[u8],
    big_endian: bool,
    from_le: fn([u8; N]) -> T,
    from_be: fn([u8; N]) -> T,
) -> Vec<T> {
    raw.chunks_exact(N)
        .map(|chunk| {
            let mut bytes = [0u8; N];
            bytes.copy_from_slice(chunk);
            if big_endian {
                from_be(bytes)
            } else {
                from_le(bytes)
            }
        })
        .collect()
}

/// Reorders column-major elements into row-major order. `values.len()` must
/// be the product of `shape` (the caller checked it).
fn fortran_to_c<T: Copy>(values: &[T], shape: &[usize]) -> Vec<T> {
    if values.is_empty() {
        return Vec::new();
    }
    // Column-major strides: the first axis varies fastest.
    let mut fortran_strides = Vec::with_capacity(shape.len());
    let mut stride = 1usize;
    for &dim in shape {
        fortran_strides.push(stride);
        stride *= dim;
    }
    let mut index = vec![0usize; shape.len()];
    let mut out = Vec::with_capacity(values.len());
    for _ in 0..values.len() {
        let source: usize = index.iter().zip(&fortran_strides).map(|(i, s)| i * s).sum();
        out.push(values[source]);
        // Advance the row-major multi-index (last axis fastest).
        for axis in (0..shape.len()).rev() {
            index[axis] += 1;
            if index[axis] < shape[axis] {
                break;
            }
            index[axis] = 0;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fortran_order_is_transposed_into_c_order() {
        // numpy: np.asfortranarray(np.arange(6).reshape(2, 3)).tobytes('A') == [0,3,1,4,2,5]
        let raw: Vec<u8> = [0i32, 3, 1, 4, 2, 5]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let array = NdArray::from_raw(Element::I32, ByteOrder::Little, vec![2, 3], true, &raw)
            .expect("valid");
        assert_eq!(array.data(), &ArrayData::I32(vec![0, 1, 2, 3, 4, 5]));
    }

    #[test]
    fn big_endian_is_swapped_and_size_mismatch_is_an_error() {
        let array = NdArray::from_raw(Element::U16, ByteOrder::Big, vec![2], false, &[1, 2, 0, 5])
            .expect("valid");
        assert_eq!(array.data(), &ArrayData::U16(vec![0x0102, 5]));
        let err = NdArray::from_raw(Element::F64, ByteOrder::Little, vec![2], false, &[0; 15])
            .expect_err("short");
        assert!(err.contains("needs 16 data bytes, found 15"), "{err}");
        let err = NdArray::from_raw(
            Element::F64,
            ByteOrder::Little,
            vec![usize::MAX, 2],
            false,
            &[],
        )
        .expect_err("overflow");
        assert!(err.contains("too large"), "{err}");
    }

    #[test]
    fn descriptors_parse() {
        assert_eq!(
            parse_descriptor("<f4"),
            Some((Element::F32, ByteOrder::Little))
        );
        assert_eq!(
            parse_descriptor(">u2"),
            Some((Element::U16, ByteOrder::Big))
        );
        assert_eq!(
            parse_descriptor("|b1"),
            Some((Element::Bool, ByteOrder::Little))
        );
        assert_eq!(parse_descriptor("<U5"), None);
        assert_eq!(parse_descriptor(""), None);
    }
}
