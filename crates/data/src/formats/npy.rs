//! Minimal typed `.npy` reading and writing on top of `npyz`, with size checks before any
//! allocation so that malformed headers give errors, not aborts.

use super::io::{read_bytes, write_atomic};
use crate::error::DataError;
use npyz::WriterBuilder;
use std::path::Path;

/// The values of an `.npy` array, by dtype.
#[derive(Clone, Debug, PartialEq)]
pub enum NpyValues {
    Bool(Vec<bool>),
    U8(Vec<u8>),
    I8(Vec<i8>),
    U16(Vec<u16>),
    I16(Vec<i16>),
    U32(Vec<u32>),
    I32(Vec<i32>),
    U64(Vec<u64>),
    I64(Vec<i64>),
    F32(Vec<f32>),
    F64(Vec<f64>),
}

impl NpyValues {
    /// Number of elements.
    pub fn len(&self) -> usize {
        match self {
            NpyValues::Bool(v) => v.len(),
            NpyValues::U8(v) => v.len(),
            NpyValues::I8(v) => v.len(),
            NpyValues::U16(v) => v.len(),
            NpyValues::I16(v) => v.len(),
            NpyValues::U32(v) => v.len(),
            NpyValues::I32(v) => v.len(),
            NpyValues::U64(v) => v.len(),
            NpyValues::I64(v) => v.len(),
            NpyValues::F32(v) => v.len(),
            NpyValues::F64(v) => v.len(),
        }
    }

    /// True when there are no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// numpy name of the dtype (`uint8`, `float32`, ...).
    pub fn dtype_name(&self) -> &'static str {
        match self {
            NpyValues::Bool(_) => "bool",
            NpyValues::U8(_) => "uint8",
            NpyValues::I8(_) => "int8",
            NpyValues::U16(_) => "uint16",
            NpyValues::I16(_) => "int16",
            NpyValues::U32(_) => "uint32",
            NpyValues::I32(_) => "int32",
            NpyValues::U64(_) => "uint64",
            NpyValues::I64(_) => "int64",
            NpyValues::F32(_) => "float32",
            NpyValues::F64(_) => "float64",
        }
    }

    /// All values as f64 (exact for every integer dtype up to 2^53).
    pub fn to_f64(&self) -> Vec<f64> {
        match self {
            NpyValues::Bool(v) => v.iter().map(|&x| x as u8 as f64).collect(),
            NpyValues::U8(v) => v.iter().map(|&x| x as f64).collect(),
            NpyValues::I8(v) => v.iter().map(|&x| x as f64).collect(),
            NpyValues::U16(v) => v.iter().map(|&x| x as f64).collect(),
            NpyValues::I16(v) => v.iter().map(|&x| x as f64).collect(),
            NpyValues::U32(v) => v.iter().map(|&x| x as f64).collect(),
            NpyValues::I32(v) => v.iter().map(|&x| x as f64).collect(),
            NpyValues::U64(v) => v.iter().map(|&x| x as f64).collect(),
            NpyValues::I64(v) => v.iter().map(|&x| x as f64).collect(),
            NpyValues::F32(v) => v.iter().map(|&x| x as f64).collect(),
            NpyValues::F64(v) => v.clone(),
        }
    }
}

/// A C-order `.npy` array (Fortran-order files are reordered to C order on reading).
#[derive(Clone, Debug, PartialEq)]
pub struct NpyArray {
    pub shape: Vec<usize>,
    pub values: NpyValues,
}

fn header_data_offset(bytes: &[u8], path: &Path) -> Result<usize, DataError> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(DataError::format(path, "not an .npy file (bad magic)"));
    }
    let major = bytes[6];
    let (len, start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(DataError::Truncated {
                    path: path.to_path_buf(),
                    expected: 12,
                    actual: bytes.len() as u64,
                });
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => {
            return Err(DataError::format(
                path,
                format!("unsupported .npy version {v}"),
            ))
        }
    };
    let end = start + len;
    if end > bytes.len() {
        return Err(DataError::Truncated {
            path: path.to_path_buf(),
            expected: end as u64,
            actual: bytes.len() as u64,
        });
    }
    Ok(end)
}

/// Reorder a Fortran-order buffer of `shape` into C order.
fn fortran_to_c<T: Copy>(data: Vec<T>, shape: &[usize]) -> Vec<T> {
    if shape.len() < 2 {
        return data;
    }
    let n = data.len();
    let mut out = Vec::with_capacity(n);
    let mut idx = vec![0usize; shape.len()];
    for _ in 0..n {
        // Fortran offset of the C-order multi-index `idx`
        let mut off = 0;
        let mut stride = 1;
        for (a, &i) in idx.iter().enumerate() {
            off += i * stride;
            stride *= shape[a];
        }
        out.push(data[off]);
        for a in (0..shape.len()).rev() {
            idx[a] += 1;
            if idx[a] < shape[a] {
                break;
            }
            idx[a] = 0;
        }
    }
    out
}

/// Parse `.npy` bytes (`path` is only used in error messages).
pub fn parse_npy(bytes: &[u8], path: &Path) -> Result<NpyArray, DataError> {
    let data_start = header_data_offset(bytes, path)?;
    let npy = npyz::NpyFile::new(bytes)
        .map_err(|e| DataError::format(path, format!("bad .npy header: {e}")))?;
    let shape: Vec<usize> = npy.shape().iter().map(|&d| d as usize).collect();
    let n = shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| DataError::format(path, format!("shape {shape:?} overflows")))?;
    let fortran = npy.order() == npyz::Order::Fortran;
    let ts = match npy.dtype() {
        npyz::DType::Plain(ts) => ts.to_string(),
        other => {
            return Err(DataError::format(
                path,
                format!("unsupported structured dtype {}", other.descr()),
            ))
        }
    };
    let code = ts.get(1..).unwrap_or("");
    let item = match code {
        "b1" | "u1" | "i1" => 1,
        "u2" | "i2" => 2,
        "u4" | "i4" | "f4" => 4,
        "u8" | "i8" | "f8" => 8,
        _ => return Err(DataError::format(path, format!("unsupported dtype '{ts}'"))),
    };
    let need = n
        .checked_mul(item)
        .and_then(|b| b.checked_add(data_start))
        .ok_or_else(|| DataError::format(path, "array size overflows"))?;
    if bytes.len() < need {
        return Err(DataError::Truncated {
            path: path.to_path_buf(),
            expected: need as u64,
            actual: bytes.len() as u64,
        });
    }
    if bytes.len() > need {
        return Err(DataError::WrongSize {
            path: path.to_path_buf(),
            detail: format!(
                "{} trailing bytes after the {shape:?} '{ts}' array",
                bytes.len() - need
            ),
        });
    }
    let err = |e: std::io::Error| DataError::format(path, format!("cannot read .npy data: {e}"));
    macro_rules! read {
        ($t:ty, $v:ident) => {{
            let v: Vec<$t> = npy.into_vec::<$t>().map_err(err)?;
            NpyValues::$v(if fortran { fortran_to_c(v, &shape) } else { v })
        }};
    }
    let values = match code {
        "b1" => read!(bool, Bool),
        "u1" => read!(u8, U8),
        "i1" => read!(i8, I8),
        "u2" => read!(u16, U16),
        "i2" => read!(i16, I16),
        "u4" => read!(u32, U32),
        "i4" => read!(i32, I32),
        "u8" => read!(u64, U64),
        "i8" => read!(i64, I64),
        "f4" => read!(f32, F32),
        _ => read!(f64, F64),
    };
    if values.len() != n {
        return Err(DataError::format(
            path,
            format!("expected {n} elements, read {}", values.len()),
        ));
    }
    Ok(NpyArray { shape, values })
}

/// Read an `.npy` file.
pub fn read_npy(path: &Path) -> Result<NpyArray, DataError> {
    let bytes = read_bytes(path)?;
    parse_npy(&bytes, path)
}

/// Serialise a C-order array as `.npy` bytes (little-endian, version 1).
pub fn npy_bytes<T>(shape: &[usize], data: &[T]) -> Result<Vec<u8>, DataError>
where
    T: npyz::Serialize + npyz::AutoSerialize + Copy,
{
    let n: usize = shape.iter().product();
    if n != data.len() {
        return Err(DataError::InvalidArgument(format!(
            "npy: shape {shape:?} needs {n} values, got {}",
            data.len()
        )));
    }
    let shape64: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
    let mut out = Vec::with_capacity(std::mem::size_of_val(data) + 128);
    let io_err =
        |e: std::io::Error| DataError::InvalidArgument(format!("npy serialisation failed: {e}"));
    {
        let mut w = npyz::WriteOptions::<T>::new()
            .default_dtype()
            .shape(&shape64)
            .writer(&mut out)
            .begin_nd()
            .map_err(io_err)?;
        w.extend(data.iter().copied()).map_err(io_err)?;
        w.finish().map_err(io_err)?;
    }
    Ok(out)
}

/// Write a C-order array to an `.npy` file atomically.
pub fn write_npy<T>(path: &Path, shape: &[usize], data: &[T]) -> Result<(), DataError>
where
    T: npyz::Serialize + npyz::AutoSerialize + Copy,
{
    let bytes = npy_bytes(shape, data)?;
    write_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_fortran_reorder() {
        let p = Path::new("mem.npy");
        let data: Vec<f32> = (0..24).map(|x| x as f32 * 0.5).collect();
        let b = npy_bytes(&[2, 3, 4], &data).unwrap();
        let a = parse_npy(&b, p).unwrap();
        assert_eq!(a.shape, vec![2, 3, 4]);
        assert_eq!(a.values, NpyValues::F32(data.clone()));
        // Fortran: element (i,j,k) stored at i + 2j + 6k
        let mut f = vec![0u8; 24];
        for i in 0..2 {
            for j in 0..3 {
                for k in 0..4 {
                    f[i + 2 * j + 6 * k] = (i * 12 + j * 4 + k) as u8;
                }
            }
        }
        let c = fortran_to_c(f, &[2, 3, 4]);
        assert_eq!(c, (0..24u8).collect::<Vec<_>>());
    }

    #[test]
    fn malformed_inputs_are_errors() {
        let p = Path::new("bad.npy");
        let data: Vec<u8> = vec![1, 2, 3, 4];
        let b = npy_bytes(&[4], &data).unwrap();
        for cut in 0..b.len() {
            assert!(parse_npy(&b[..cut], p).is_err(), "cut {cut}");
        }
        let mut long = b.clone();
        long.push(0);
        assert!(matches!(
            parse_npy(&long, p),
            Err(DataError::WrongSize { .. })
        ));
        assert!(parse_npy(b"hello world, not npy", p).is_err());
        // header claims an enormous shape: must be a size error, not an allocation
        let mut huge = b"\x93NUMPY\x01\x00".to_vec();
        let mut hdr = "{'descr': '<f8', 'fortran_order': False, 'shape': (100000000000, 100000), }"
            .to_string();
        while !(10 + hdr.len() + 1).is_multiple_of(64) {
            hdr.push(' ');
        }
        hdr.push('\n');
        huge.extend_from_slice(&(hdr.len() as u16).to_le_bytes());
        huge.extend_from_slice(hdr.as_bytes());
        assert!(parse_npy(&huge, p).is_err());
    }
}
