//! A general PLY reader/writer (ASCII, binary little- and big-endian, any
//! property order, list properties) shared by the mesh loader, point clouds
//! and splat files. Written here rather than taken from a crate because every
//! caller needs columns by name with strict, file-named errors on truncated
//! or malformed input, and the format is small.

use std::path::Path;

use crate::error::{CoreError, Result};

/// Scalar type of a property.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarType {
    fn parse(name: &str) -> Option<ScalarType> {
        Some(match name {
            "char" | "int8" => ScalarType::I8,
            "uchar" | "uint8" => ScalarType::U8,
            "short" | "int16" => ScalarType::I16,
            "ushort" | "uint16" => ScalarType::U16,
            "int" | "int32" => ScalarType::I32,
            "uint" | "uint32" => ScalarType::U32,
            "float" | "float32" => ScalarType::F32,
            "double" | "float64" => ScalarType::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            ScalarType::I8 | ScalarType::U8 => 1,
            ScalarType::I16 | ScalarType::U16 => 2,
            ScalarType::I32 | ScalarType::U32 | ScalarType::F32 => 4,
            ScalarType::F64 => 8,
        }
    }
    fn name(self) -> &'static str {
        match self {
            ScalarType::I8 => "char",
            ScalarType::U8 => "uchar",
            ScalarType::I16 => "short",
            ScalarType::U16 => "ushort",
            ScalarType::I32 => "int",
            ScalarType::U32 => "uint",
            ScalarType::F32 => "float",
            ScalarType::F64 => "double",
        }
    }
}

/// A property of an element: a scalar, or a list with a count type.
#[derive(Debug, Clone, PartialEq)]
pub struct Property {
    pub name: String,
    pub scalar: ScalarType,
    /// For list properties, the type of the count.
    pub list_count: Option<ScalarType>,
}

/// Values of one property over all items of an element.
#[derive(Debug, Clone, PartialEq)]
pub enum Column {
    Scalar(Vec<f64>),
    List(Vec<Vec<f64>>),
}

/// An element (e.g. `vertex`, `face`) with its columns in header order.
#[derive(Debug, Clone, PartialEq)]
pub struct Element {
    pub name: String,
    pub count: usize,
    pub properties: Vec<Property>,
    pub columns: Vec<Column>,
}

impl Element {
    /// A scalar column by name.
    pub fn scalar(&self, name: &str) -> Option<&[f64]> {
        let i = self.properties.iter().position(|p| p.name == name)?;
        match &self.columns[i] {
            Column::Scalar(v) => Some(v),
            Column::List(_) => None,
        }
    }
    /// A list column by name.
    pub fn list(&self, name: &str) -> Option<&[Vec<f64>]> {
        let i = self.properties.iter().position(|p| p.name == name)?;
        match &self.columns[i] {
            Column::List(v) => Some(v),
            Column::Scalar(_) => None,
        }
    }
}

/// Storage format of a PLY body.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

/// A parsed PLY file.
#[derive(Debug, Clone, PartialEq)]
pub struct PlyFile {
    pub format: Format,
    pub comments: Vec<String>,
    pub elements: Vec<Element>,
}

impl PlyFile {
    pub fn element(&self, name: &str) -> Option<&Element> {
        self.elements.iter().find(|e| e.name == name)
    }
}

/// Reads a PLY file.
pub fn read(path: &Path) -> Result<PlyFile> {
    let bytes = std::fs::read(path).map_err(|e| CoreError::io(path, e))?;
    parse(&bytes).map_err(|m| CoreError::parse(path, m))
}

/// Parses PLY bytes; errors are plain messages for the caller to attach a path to.
pub fn parse(bytes: &[u8]) -> std::result::Result<PlyFile, String> {
    const END: &[u8] = b"end_header";
    let end = bytes
        .windows(END.len())
        .position(|w| w == END)
        .ok_or("not a PLY file: no `end_header` line")?;
    let mut body_start = end + END.len();
    // The header ends with a newline ("\n" or "\r\n").
    while body_start < bytes.len() && (bytes[body_start] == b'\r' || bytes[body_start] == b' ') {
        body_start += 1;
    }
    if body_start < bytes.len() && bytes[body_start] == b'\n' {
        body_start += 1;
    }
    let header = std::str::from_utf8(&bytes[..end]).map_err(|_| "PLY header is not text")?;
    let mut lines = header.lines().map(str::trim).filter(|l| !l.is_empty());
    if lines.next() != Some("ply") {
        return Err("not a PLY file: first line is not `ply`".into());
    }
    let mut format = None;
    let mut comments = Vec::new();
    let mut elements: Vec<Element> = Vec::new();
    for line in lines {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words[0] {
            "format" => {
                format = Some(match words.get(1).copied() {
                    Some("ascii") => Format::Ascii,
                    Some("binary_little_endian") => Format::BinaryLittleEndian,
                    Some("binary_big_endian") => Format::BinaryBigEndian,
                    other => return Err(format!("unknown PLY format {other:?}")),
                })
            }
            "comment" | "obj_info" => {
                comments.push(line.split_once(' ').map(|x| x.1).unwrap_or("").to_string())
            }
            "element" => {
                let (Some(name), Some(count)) = (words.get(1), words.get(2)) else {
                    return Err(format!("malformed element line `{line}`"));
                };
                let count: usize = count
                    .parse()
                    .map_err(|_| format!("bad element count in `{line}`"))?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    properties: vec![],
                    columns: vec![],
                });
            }
            "property" => {
                let element = elements.last_mut().ok_or("property before any element")?;
                let prop = if words.get(1) == Some(&"list") {
                    if words.len() != 5 {
                        return Err(format!("malformed list property `{line}`"));
                    }
                    let count = ScalarType::parse(words[2])
                        .ok_or_else(|| format!("unknown type in `{line}`"))?;
                    let scalar = ScalarType::parse(words[3])
                        .ok_or_else(|| format!("unknown type in `{line}`"))?;
                    Property {
                        name: words[4].to_string(),
                        scalar,
                        list_count: Some(count),
                    }
                } else {
                    if words.len() != 3 {
                        return Err(format!("malformed property `{line}`"));
                    }
                    let scalar = ScalarType::parse(words[1])
                        .ok_or_else(|| format!("unknown type in `{line}`"))?;
                    Property {
                        name: words[2].to_string(),
                        scalar,
                        list_count: None,
                    }
                };
                element.properties.push(prop);
            }
            other => return Err(format!("unknown PLY header keyword `{other}`")),
        }
    }
    let format = format.ok_or("PLY header has no format line")?;
    let body = &bytes[body_start..];
    let used = match format {
        Format::Ascii => read_ascii(body, &mut elements)?,
        _ => read_binary(body, &mut elements, format == Format::BinaryBigEndian)?,
    };
    check_nothing_after(&body[used..], &elements)?;
    Ok(PlyFile {
        format,
        comments,
        elements,
    })
}

/// The body must end where the header's elements do: bytes left over mean
/// a count was lowered or a property line lost, and reading on as if
/// nothing were wrong dropped splats or shifted every column into the
/// next. A final line break (or an ASCII body's trailing spaces) is
/// allowed, as writers add one.
fn check_nothing_after(rest: &[u8], elements: &[Element]) -> std::result::Result<(), String> {
    let line_break = rest.len() <= 2 && rest.iter().all(|b| matches!(b, b'\n' | b'\r'));
    if line_break {
        return Ok(());
    }
    let counts = elements
        .iter()
        .map(|e| format!("{} {}", e.name, e.count))
        .collect::<Vec<_>>()
        .join(", ");
    Err(format!(
        "{} bytes follow the last element: the header's elements ({counts}) and their properties do not describe the whole file",
        rest.len()
    ))
}

/// Columns for `e`'s items, with room reserved for as many as a body of
/// `body_len` bytes can hold (an item takes at least one byte in either
/// encoding): the header's count comes from the file, and a damaged one
/// asked for terabytes before the body was read.
fn empty_columns(e: &Element, body_len: usize) -> Vec<Column> {
    let room = e.count.min(body_len);
    e.properties
        .iter()
        .map(|p| match p.list_count {
            None => Column::Scalar(Vec::with_capacity(room)),
            Some(_) => Column::List(Vec::with_capacity(room)),
        })
        .collect()
}

/// How many of `e`'s items the body holds: none for an element without
/// properties, whatever its count says (a damaged one looped 2⁶⁴ times).
fn items_to_read(e: &Element) -> usize {
    if e.properties.is_empty() { 0 } else { e.count }
}

/// Reads the elements from an ASCII body; returns how many of its bytes
/// they took (trailing whitespace included).
fn read_ascii(body: &[u8], elements: &mut [Element]) -> std::result::Result<usize, String> {
    let text = std::str::from_utf8(body).map_err(|_| "ASCII PLY body is not text")?;
    let mut tokens = text.split_ascii_whitespace();
    for e in elements.iter_mut() {
        let mut columns = empty_columns(e, body.len());
        for item in 0..items_to_read(e) {
            let mut next = |what: &str| -> std::result::Result<f64, String> {
                let t = tokens.next().ok_or_else(|| {
                    format!(
                        "file ends early: element `{}` item {item} of {} ({what})",
                        e.name, e.count
                    )
                })?;
                t.parse::<f64>()
                    .map_err(|_| format!("bad number `{t}` in element `{}` item {item}", e.name))
            };
            for (p, col) in e.properties.iter().zip(columns.iter_mut()) {
                match col {
                    Column::Scalar(v) => v.push(next(&p.name)?),
                    Column::List(v) => {
                        let n = next(&p.name)?;
                        if !(0.0..=1e6).contains(&n) {
                            return Err(format!(
                                "bad list length {n} in element `{}` item {item}",
                                e.name
                            ));
                        }
                        let mut list = Vec::with_capacity(n as usize);
                        for _ in 0..n as usize {
                            list.push(next(&p.name)?);
                        }
                        v.push(list);
                    }
                }
            }
        }
        e.columns = columns;
    }
    Ok(match tokens.next() {
        // Where the first token left over starts.
        Some(t) => t.as_ptr() as usize - text.as_ptr() as usize,
        None => body.len(),
    })
}

fn read_scalar(bytes: &[u8], t: ScalarType, big: bool) -> f64 {
    macro_rules! get {
        ($ty:ty, $n:expr) => {{
            let mut a = [0u8; $n];
            a.copy_from_slice(&bytes[..$n]);
            if big {
                <$ty>::from_be_bytes(a) as f64
            } else {
                <$ty>::from_le_bytes(a) as f64
            }
        }};
    }
    match t {
        ScalarType::I8 => bytes[0] as i8 as f64,
        ScalarType::U8 => bytes[0] as f64,
        ScalarType::I16 => get!(i16, 2),
        ScalarType::U16 => get!(u16, 2),
        ScalarType::I32 => get!(i32, 4),
        ScalarType::U32 => get!(u32, 4),
        ScalarType::F32 => get!(f32, 4),
        ScalarType::F64 => get!(f64, 8),
    }
}

/// Reads the elements from a binary body; returns how many of its bytes
/// they took.
fn read_binary(
    body: &[u8],
    elements: &mut [Element],
    big: bool,
) -> std::result::Result<usize, String> {
    let mut at = 0usize;
    for e in elements.iter_mut() {
        let mut columns = empty_columns(e, body.len());
        let fixed: Option<usize> = e
            .properties
            .iter()
            .map(|p| p.list_count.is_none().then(|| p.scalar.size()))
            .sum();
        if let Some(stride) = fixed {
            let need = stride.checked_mul(e.count).ok_or("element too large")?;
            if body.len() < at + need {
                return Err(format!(
                    "file is truncated: element `{}` needs {} bytes for {} items, {} remain",
                    e.name,
                    need,
                    e.count,
                    body.len().saturating_sub(at)
                ));
            }
        }
        for item in 0..items_to_read(e) {
            for (p, col) in e.properties.iter().zip(columns.iter_mut()) {
                let mut take = |t: ScalarType| -> std::result::Result<f64, String> {
                    let n = t.size();
                    if at + n > body.len() {
                        return Err(format!(
                            "file is truncated in element `{}` item {item} of {}",
                            e.name, e.count
                        ));
                    }
                    let v = read_scalar(&body[at..], t, big);
                    at += n;
                    Ok(v)
                };
                match col {
                    Column::Scalar(v) => v.push(take(p.scalar)?),
                    Column::List(v) => {
                        let n = take(p.list_count.unwrap())?;
                        if !(0.0..=1e6).contains(&n) {
                            return Err(format!(
                                "bad list length {n} in element `{}` item {item}",
                                e.name
                            ));
                        }
                        let mut list = Vec::with_capacity(n as usize);
                        for _ in 0..n as usize {
                            list.push(take(p.scalar)?);
                        }
                        v.push(list);
                    }
                }
            }
        }
        e.columns = columns;
    }
    Ok(at)
}

/// Serialises scalar-only elements (plus optional list columns) as binary little-endian PLY.
pub fn to_binary_le(file: &PlyFile) -> Vec<u8> {
    let mut out = String::from("ply\nformat binary_little_endian 1.0\n");
    for c in &file.comments {
        out.push_str(&format!("comment {c}\n"));
    }
    for e in &file.elements {
        out.push_str(&format!("element {} {}\n", e.name, e.count));
        for p in &e.properties {
            match p.list_count {
                None => out.push_str(&format!("property {} {}\n", p.scalar.name(), p.name)),
                Some(c) => out.push_str(&format!(
                    "property list {} {} {}\n",
                    c.name(),
                    p.scalar.name(),
                    p.name
                )),
            }
        }
    }
    out.push_str("end_header\n");
    let mut bytes = out.into_bytes();
    fn put(bytes: &mut Vec<u8>, t: ScalarType, v: f64) {
        match t {
            ScalarType::I8 => bytes.push(v as i8 as u8),
            ScalarType::U8 => bytes.push(v as u8),
            ScalarType::I16 => bytes.extend((v as i16).to_le_bytes()),
            ScalarType::U16 => bytes.extend((v as u16).to_le_bytes()),
            ScalarType::I32 => bytes.extend((v as i32).to_le_bytes()),
            ScalarType::U32 => bytes.extend((v as u32).to_le_bytes()),
            ScalarType::F32 => bytes.extend((v as f32).to_le_bytes()),
            ScalarType::F64 => bytes.extend(v.to_le_bytes()),
        }
    }
    for e in &file.elements {
        for i in 0..e.count {
            for (p, col) in e.properties.iter().zip(&e.columns) {
                match col {
                    Column::Scalar(v) => put(&mut bytes, p.scalar, v[i]),
                    Column::List(v) => {
                        put(&mut bytes, p.list_count.unwrap(), v[i].len() as f64);
                        for x in &v[i] {
                            put(&mut bytes, p.scalar, *x);
                        }
                    }
                }
            }
        }
    }
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> PlyFile {
        PlyFile {
            format: Format::BinaryLittleEndian,
            comments: vec!["made by a test".into()],
            elements: vec![
                Element {
                    name: "vertex".into(),
                    count: 3,
                    properties: vec![
                        Property {
                            name: "x".into(),
                            scalar: ScalarType::F32,
                            list_count: None,
                        },
                        Property {
                            name: "y".into(),
                            scalar: ScalarType::F32,
                            list_count: None,
                        },
                        Property {
                            name: "z".into(),
                            scalar: ScalarType::F64,
                            list_count: None,
                        },
                        Property {
                            name: "red".into(),
                            scalar: ScalarType::U8,
                            list_count: None,
                        },
                    ],
                    columns: vec![
                        Column::Scalar(vec![0.0, 1.0, 0.0]),
                        Column::Scalar(vec![0.0, 0.0, 1.0]),
                        Column::Scalar(vec![0.5, 0.25, -1.0]),
                        Column::Scalar(vec![255.0, 0.0, 7.0]),
                    ],
                },
                Element {
                    name: "face".into(),
                    count: 1,
                    properties: vec![Property {
                        name: "vertex_indices".into(),
                        scalar: ScalarType::I32,
                        list_count: Some(ScalarType::U8),
                    }],
                    columns: vec![Column::List(vec![vec![0.0, 1.0, 2.0]])],
                },
            ],
        }
    }

    #[test]
    fn binary_round_trip() {
        let file = sample();
        let back = parse(&to_binary_le(&file)).unwrap();
        assert_eq!(back, file);
    }

    #[test]
    fn ascii_any_property_order() {
        let text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float z\nproperty float x\nproperty float y\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n3 1 2\n6 4 5\n3 0 1 1\n";
        let ply = parse(text.as_bytes()).unwrap();
        let v = ply.element("vertex").unwrap();
        assert_eq!(v.scalar("x").unwrap(), &[1.0, 4.0]);
        assert_eq!(v.scalar("z").unwrap(), &[3.0, 6.0]);
        assert_eq!(
            ply.element("face").unwrap().list("vertex_indices").unwrap()[0],
            vec![0.0, 1.0, 1.0]
        );
    }

    #[test]
    fn truncated_and_malformed_files_are_errors() {
        let bytes = to_binary_le(&sample());
        for cut in [bytes.len() - 1, bytes.len() - 20, 60] {
            assert!(parse(&bytes[..cut]).is_err(), "cut at {cut} parsed");
        }
        assert!(
            parse(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n")
                .is_err()
        );
        assert!(parse(b"hello").is_err());
        assert!(parse(b"ply\nformat weird 1.0\nend_header\n").is_err());
    }

    /// A lowered count or a lost property line leaves bytes the header does
    /// not describe; they are an error, not splats silently dropped or
    /// columns shifted. A final line break is not.
    #[test]
    fn bytes_the_header_does_not_describe_are_errors() {
        let bytes = to_binary_le(&sample());
        let end = bytes.windows(10).position(|w| w == b"end_header").unwrap();
        let header = std::str::from_utf8(&bytes[..end]).unwrap();
        for (what, damaged) in [
            (
                "lowered count",
                header.replacen("element vertex 3", "element vertex 2", 1),
            ),
            (
                "lost property",
                header.replacen("property float y\n", "", 1),
            ),
        ] {
            let file = [damaged.as_bytes(), &bytes[end..]].concat();
            let message = parse(&file).unwrap_err();
            assert!(
                message.contains("follow the last element"),
                "{what}: {message}"
            );
        }
        let mut with_newline = bytes.clone();
        with_newline.push(b'\n');
        assert_eq!(parse(&with_newline).unwrap(), sample());
        let ascii = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n2\n";
        assert!(
            parse(ascii.as_bytes())
                .unwrap_err()
                .contains("follow the last element")
        );
        let ascii =
            "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n2\n\n  \n";
        assert!(parse(ascii.as_bytes()).is_ok());
    }

    /// A damaged count must not be taken at its word: reserving room for
    /// 10¹³ items aborted the process (an allocation failure, not an error)
    /// before the body was read, and an element without properties looped
    /// over its count.
    #[test]
    fn absurd_element_counts_are_errors_not_aborts() {
        for format in ["ascii", "binary_little_endian"] {
            let file = format!(
                "ply\nformat {format} 1.0\nelement vertex 9999999999999\nproperty float x\nend_header\n1 2 3 4\n"
            );
            let message = parse(file.as_bytes()).unwrap_err();
            assert!(
                message.contains("ends early") || message.contains("truncated"),
                "{format}: {message}"
            );
        }
        let empty = b"ply\nformat ascii 1.0\nelement nothing 18446744073709551615\nend_header\n";
        let ply = parse(empty).unwrap();
        assert_eq!(ply.element("nothing").unwrap().columns.len(), 0);
    }
}
