//! The PLY header: the metadata read, and checked, before any data.

use std::io::{BufRead, Read};
use std::path::Path;

use super::PlyError;

/// Longest header accepted, bytes (3DGS headers are ~1.5 KB).
const MAX_HEADER_BYTES: u64 = 1 << 20;

/// How the records after `end_header` are encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Encoding {
    /// One record per line, values separated by whitespace.
    Ascii,
    /// Packed binary, little endian.
    BinaryLe,
    /// Packed binary, big endian.
    BinaryBe,
}

/// One of the eight PLY scalar types.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    /// Both spellings of the PLY spec (`uchar` and `uint8`, ...).
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    /// Size in binary files, bytes.
    pub(crate) fn size(self) -> u64 {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    /// The classic PLY name.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Self::I8 => "char",
            Self::U8 => "uchar",
            Self::I16 => "short",
            Self::U16 => "ushort",
            Self::I32 => "int",
            Self::U32 => "uint",
            Self::F32 => "float",
            Self::F64 => "double",
        }
    }

    /// Whether the type is `float` or `double`.
    pub(crate) fn is_float(self) -> bool {
        matches!(self, Self::F32 | Self::F64)
    }
}

/// A property: a scalar, or a list with its length type and item type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

impl Kind {
    /// The type as written in a header (`float`, `list uchar int`).
    pub(crate) fn describe(self) -> String {
        match self {
            Self::Scalar(s) => s.name().to_string(),
            Self::List { count, item } => format!("list {} {}", count.name(), item.name()),
        }
    }
}

/// One property of an element.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Property {
    pub(crate) name: String,
    pub(crate) kind: Kind,
}

/// One element: a name, a record count and the properties of each record.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Element {
    pub(crate) name: String,
    pub(crate) count: u64,
    pub(crate) properties: Vec<Property>,
}

impl Element {
    /// Bytes per binary record when no property is a list.
    pub(crate) fn fixed_size(&self) -> Option<u64> {
        self.properties
            .iter()
            .map(|p| match p.kind {
                Kind::Scalar(s) => Some(s.size()),
                Kind::List { .. } => None,
            })
            .sum()
    }

    /// Fewest bytes one record can take: binary with empty lists, or ASCII `0 ` per value.
    pub(crate) fn min_record_bytes(&self, encoding: Encoding) -> u64 {
        match encoding {
            Encoding::Ascii => 2 * self.properties.len() as u64,
            Encoding::BinaryLe | Encoding::BinaryBe => self
                .properties
                .iter()
                .map(|p| match p.kind {
                    Kind::Scalar(s) => s.size(),
                    Kind::List { count, .. } => count.size(),
                })
                .sum(),
        }
    }

    /// The index and scalar type of property `name`; `None` if absent, `Err` type if a list.
    pub(crate) fn scalar(&self, name: &str) -> Option<(usize, Result<Scalar, Kind>)> {
        let i = self.properties.iter().position(|p| p.name == name)?;
        Some(match self.properties[i].kind {
            Kind::Scalar(s) => (i, Ok(s)),
            k @ Kind::List { .. } => (i, Err(k)),
        })
    }
}

/// A parsed header.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Header {
    pub(crate) encoding: Encoding,
    pub(crate) elements: Vec<Element>,
    /// Where the data starts: the byte after `end_header\n`.
    pub(crate) data_offset: u64,
    /// Number of header lines (ASCII data starts on the next).
    pub(crate) lines: usize,
}

impl Header {
    /// The index and description of element `name`.
    pub(crate) fn element(&self, name: &str) -> Option<(usize, &Element)> {
        self.elements
            .iter()
            .enumerate()
            .find(|(_, e)| e.name == name)
    }
}

/// Reads the header from the start of `r`, stopping right after `end_header`.
pub(crate) fn read_header(r: &mut impl BufRead, path: &Path) -> Result<Header, PlyError> {
    let mut offset = 0u64;
    let mut line_no = 0usize;
    let mut buf = Vec::new();
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    let err = |line: usize, message: String| PlyError::Header {
        path: path.to_path_buf(),
        line,
        message,
    };
    loop {
        buf.clear();
        let limit = MAX_HEADER_BYTES - offset;
        let n = (&mut *r)
            .take(limit)
            .read_until(b'\n', &mut buf)
            .map_err(|e| PlyError::Io {
                path: path.to_path_buf(),
                action: "read",
                message: e.to_string(),
            })?;
        line_no += 1;
        offset += n as u64;
        if n == 0 {
            return Err(err(line_no, "file ends before `end_header`".into()));
        }
        if offset >= MAX_HEADER_BYTES && !buf.ends_with(b"\n") {
            return Err(err(
                line_no,
                format!("no `end_header` in the first {MAX_HEADER_BYTES} bytes"),
            ));
        }
        let mut raw: &[u8] = &buf;
        raw = raw.strip_suffix(b"\n").unwrap_or(raw);
        raw = raw.strip_suffix(b"\r").unwrap_or(raw);
        if line_no == 1 {
            if raw != b"ply" {
                let found: String = String::from_utf8_lossy(raw).chars().take(40).collect();
                return Err(PlyError::NotPly {
                    path: path.to_path_buf(),
                    found,
                });
            }
            continue;
        }
        let Ok(text) = std::str::from_utf8(raw) else {
            return Err(err(line_no, "line is not UTF-8 text".into()));
        };
        let mut words = text.split_ascii_whitespace();
        let Some(keyword) = words.next() else {
            continue;
        };
        let rest: Vec<&str> = words.collect();
        match keyword {
            "comment" | "obj_info" => {}
            "format" => {
                if encoding.is_some() {
                    return Err(err(line_no, "second `format` line".into()));
                }
                let unknown = || PlyError::UnknownFormat {
                    path: path.to_path_buf(),
                    line: line_no,
                    format: rest.join(" "),
                };
                if rest.len() != 2 || rest[1] != "1.0" {
                    return Err(unknown());
                }
                encoding = Some(match rest[0] {
                    "ascii" => Encoding::Ascii,
                    "binary_little_endian" => Encoding::BinaryLe,
                    "binary_big_endian" => Encoding::BinaryBe,
                    _ => return Err(unknown()),
                });
            }
            "element" => {
                let [name, count] = rest[..] else {
                    return Err(err(
                        line_no,
                        format!("expected `element <name> <count>`, found {text:?}"),
                    ));
                };
                let count: u64 = count.parse().map_err(|_| {
                    err(
                        line_no,
                        format!("element `{name}`: count `{count}` is not a non-negative integer"),
                    )
                })?;
                if elements.iter().any(|e| e.name == name) {
                    return Err(err(line_no, format!("second element named `{name}`")));
                }
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    properties: Vec::new(),
                });
            }
            "property" => {
                let Some(element) = elements.last_mut() else {
                    return Err(err(line_no, "`property` before any `element`".into()));
                };
                let property = parse_property(&rest, text, line_no, path)?;
                if element.properties.iter().any(|p| p.name == property.name) {
                    return Err(err(
                        line_no,
                        format!(
                            "element `{}` has a second property named `{}`",
                            element.name, property.name
                        ),
                    ));
                }
                element.properties.push(property);
            }
            "end_header" => {
                if !rest.is_empty() {
                    return Err(err(
                        line_no,
                        format!("unexpected text after `end_header`: {text:?}"),
                    ));
                }
                let Some(encoding) = encoding else {
                    return Err(err(line_no, "no `format` line before `end_header`".into()));
                };
                return Ok(Header {
                    encoding,
                    elements,
                    data_offset: offset,
                    lines: line_no,
                });
            }
            other => {
                return Err(err(
                    line_no,
                    format!("unknown keyword `{other}` (line {text:?})"),
                ));
            }
        }
    }
}

/// `<type> <name>` or `list <count type> <item type> <name>`.
fn parse_property(
    rest: &[&str],
    text: &str,
    line: usize,
    path: &Path,
) -> Result<Property, PlyError> {
    let unknown = |property: &str, ty: &str| PlyError::UnknownType {
        path: path.to_path_buf(),
        line,
        property: property.to_string(),
        ty: ty.to_string(),
    };
    match rest {
        ["list", count, item, name] => {
            let c = Scalar::parse(count).ok_or_else(|| unknown(name, count))?;
            let i = Scalar::parse(item).ok_or_else(|| unknown(name, item))?;
            if c.is_float() {
                return Err(PlyError::Header {
                    path: path.to_path_buf(),
                    line,
                    message: format!("list `{name}` has a floating-point length type `{count}`"),
                });
            }
            Ok(Property {
                name: name.to_string(),
                kind: Kind::List { count: c, item: i },
            })
        }
        [ty, name] if *ty != "list" => Ok(Property {
            name: name.to_string(),
            kind: Kind::Scalar(Scalar::parse(ty).ok_or_else(|| unknown(name, ty))?),
        }),
        _ => Err(PlyError::Header {
            path: path.to_path_buf(),
            line,
            message: format!(
                "expected `property <type> <name>` or `property list <type> <type> <name>`, found {text:?}"
            ),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Header, PlyError> {
        read_header(&mut text.as_bytes(), Path::new("t.ply"))
    }

    #[test]
    fn both_type_spellings_lists_and_crlf() {
        let text = "ply\r\nformat binary_big_endian 1.0\r\nobj_info x\r\nelement v 2\r\n\
             property uint8 a\r\nproperty float64 b\r\nproperty list uchar int32 c\r\n\
             end_header\r\nDATA";
        let h = parse(text).unwrap();
        assert_eq!(h.encoding, Encoding::BinaryBe);
        assert_eq!(h.data_offset as usize, text.find("DATA").unwrap());
        assert_eq!(h.lines, 8);
        let v = &h.elements[0];
        assert_eq!((v.name.as_str(), v.count), ("v", 2));
        assert_eq!(v.fixed_size(), None);
        assert_eq!(v.min_record_bytes(Encoding::BinaryBe), 1 + 8 + 1);
        assert_eq!(v.scalar("b"), Some((1, Ok(Scalar::F64))));
        assert!(matches!(v.scalar("c"), Some((2, Err(Kind::List { .. })))));
    }

    #[test]
    fn malformed_lines_are_named() {
        let e = parse("ply\nformat ascii 1.0\nproperty float x\nend_header\n").unwrap_err();
        assert!(
            e.to_string()
                .contains("line 3: `property` before any `element`"),
            "{e}"
        );
        let e =
            parse("ply\nformat ascii 1.0\nelement v 1\nproperty list float int c\nend_header\n")
                .unwrap_err();
        assert!(e.to_string().contains("floating-point length type"), "{e}");
        let e = parse("ply\nelement v 1\nend_header\n").unwrap_err();
        assert!(e.to_string().contains("no `format` line"), "{e}");
        let e = parse("ply\nformat ascii 1.0\nformat ascii 1.0\nend_header\n").unwrap_err();
        assert!(matches!(e, PlyError::Header { line: 3, .. }), "{e}");
    }
}
