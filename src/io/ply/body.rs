//! The data after the header: decoding the records of one element, skipping the ones before it.

use std::fs::File;
use std::io::{self, BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

use super::PlyError;
use super::header::{Element, Encoding, Header, Kind, Scalar, read_header};

/// Called once per record of the wanted element with its index and the value of every property
/// (lists, which no reader here needs, give NaN).
pub(crate) type Visit<'a> = dyn FnMut(u64, &[f64]) -> Result<(), PlyError> + 'a;

/// An open PLY file whose header has been read.
#[derive(Debug)]
pub(crate) struct Source {
    reader: BufReader<File>,
    path: PathBuf,
    header: Header,
    /// Current byte offset.
    pos: u64,
    /// File length, bytes.
    len: u64,
    /// Last line read (ASCII), from 1.
    line: usize,
}

impl Source {
    /// Opens `path` and reads its header; no data yet.
    pub(crate) fn open(path: &Path) -> Result<Self, PlyError> {
        let io_err = |action: &'static str| {
            move |e: io::Error| PlyError::Io {
                path: path.to_path_buf(),
                action,
                message: e.to_string(),
            }
        };
        let file = File::open(path).map_err(io_err("open"))?;
        let len = file.metadata().map_err(io_err("stat"))?.len();
        if len == 0 {
            return Err(PlyError::Empty {
                path: path.to_path_buf(),
            });
        }
        let mut reader = BufReader::with_capacity(1 << 16, file);
        let header = read_header(&mut reader, path)?;
        Ok(Self {
            reader,
            path: path.to_path_buf(),
            pos: header.data_offset,
            line: header.lines,
            header,
            len,
        })
    }

    /// The parsed header.
    pub(crate) fn header(&self) -> &Header {
        &self.header
    }

    /// How many records of `el` could at most follow the header (a safe preallocation).
    pub(crate) fn capacity_hint(&self, el: &Element) -> usize {
        let available = self.len.saturating_sub(self.header.data_offset);
        let min = el.min_record_bytes(self.header.encoding).max(1);
        usize::try_from(el.count.min(available / min)).unwrap_or(0)
    }

    /// Decodes every record of element `target` through `visit`; the elements before it are
    /// read past, the ones after it are not read.
    pub(crate) fn read_element(
        &mut self,
        target: usize,
        visit: &mut Visit<'_>,
    ) -> Result<(), PlyError> {
        let elements = self.header.elements.clone();
        for (i, el) in elements.iter().enumerate().take(target + 1) {
            let call = i == target;
            match self.header.encoding {
                Encoding::Ascii => self.ascii_element(el, visit, call)?,
                Encoding::BinaryLe => self.binary_element(el, false, visit, call)?,
                Encoding::BinaryBe => self.binary_element(el, true, visit, call)?,
            }
        }
        Ok(())
    }

    fn binary_element(
        &mut self,
        el: &Element,
        big: bool,
        visit: &mut Visit<'_>,
        call: bool,
    ) -> Result<(), PlyError> {
        let available = self.len.saturating_sub(self.pos);
        let mut values = vec![f64::NAN; el.properties.len()];
        if let Some(size) = el.fixed_size() {
            let total = el.count.checked_mul(size);
            if total.is_none_or(|t| t > available) {
                // size > 0 here, else total would be 0.
                let record = available / size;
                return Err(self.truncated(
                    el,
                    record,
                    self.pos.saturating_add((record + 1) * size),
                ));
            }
            let total = total.unwrap_or(0);
            if !call {
                return self.skip(total, el, 0);
            }
            let mut buf = vec![0u8; usize::try_from(size).unwrap_or(0)];
            for record in 0..el.count {
                self.read_exact(&mut buf, el, record)?;
                let mut at = 0usize;
                for (v, p) in values.iter_mut().zip(&el.properties) {
                    if let Kind::Scalar(s) = p.kind {
                        *v = decode(s, &buf[at..], big);
                        at += s.size() as usize;
                    }
                }
                visit(record, &values)?;
            }
            return Ok(());
        }
        let min = el.min_record_bytes(self.header.encoding);
        if el.count.checked_mul(min).is_none_or(|t| t > available) {
            return Err(self.too_many(el, min, available));
        }
        let mut buf = [0u8; 8];
        for record in 0..el.count {
            for (v, p) in values.iter_mut().zip(&el.properties) {
                match p.kind {
                    Kind::Scalar(s) => {
                        let b = &mut buf[..s.size() as usize];
                        self.read_exact(b, el, record)?;
                        *v = decode(s, b, big);
                    }
                    Kind::List { count, item } => {
                        let b = &mut buf[..count.size() as usize];
                        self.read_exact(b, el, record)?;
                        let n = decode(count, b, big);
                        if n < 0.0 {
                            return Err(PlyError::Value {
                                path: self.path.clone(),
                                element: el.name.clone(),
                                record,
                                property: p.name.clone(),
                                message: format!("negative list length {n}"),
                            });
                        }
                        // n ≤ u32::MAX, item size ≤ 8: no overflow.
                        let bytes = n as u64 * item.size();
                        self.skip(bytes, el, record)?;
                        *v = f64::NAN;
                    }
                }
            }
            if call {
                visit(record, &values)?;
            }
        }
        Ok(())
    }

    fn ascii_element(
        &mut self,
        el: &Element,
        visit: &mut Visit<'_>,
        call: bool,
    ) -> Result<(), PlyError> {
        if el.properties.is_empty() {
            return Ok(());
        }
        let available = self.len.saturating_sub(self.pos);
        let min = el.min_record_bytes(Encoding::Ascii);
        // The last value of the file may lack its newline: one byte of slack.
        if el
            .count
            .checked_mul(min)
            .is_none_or(|t| t > available.saturating_add(1))
        {
            return Err(self.too_many(el, min, available));
        }
        let mut values = vec![f64::NAN; el.properties.len()];
        let mut line = Vec::new();
        let mut record = 0u64;
        while record < el.count {
            line.clear();
            let n = self
                .reader
                .read_until(b'\n', &mut line)
                .map_err(|e| self.io("read", e))?;
            self.line += 1;
            let ascii_err = |message: String| PlyError::Ascii {
                path: self.path.clone(),
                line: self.line,
                element: el.name.clone(),
                record,
                message,
            };
            if n == 0 {
                return Err(ascii_err(format!(
                    "file ends after {record} of the {} records the header declares",
                    el.count
                )));
            }
            self.pos += n as u64;
            let Ok(text) = std::str::from_utf8(&line) else {
                return Err(ascii_err("line is not UTF-8 text".into()));
            };
            if text.trim().is_empty() {
                continue;
            }
            parse_record(text, el, &mut values).map_err(ascii_err)?;
            if call {
                visit(record, &values)?;
            }
            record += 1;
        }
        Ok(())
    }

    fn read_exact(&mut self, buf: &mut [u8], el: &Element, record: u64) -> Result<(), PlyError> {
        let end = self.pos + buf.len() as u64;
        match self.reader.read_exact(buf) {
            Ok(()) => {
                self.pos = end;
                Ok(())
            }
            Err(e) if e.kind() == io::ErrorKind::UnexpectedEof => {
                Err(self.truncated(el, record, end))
            }
            Err(e) => Err(self.io("read", e)),
        }
    }

    fn skip(&mut self, bytes: u64, el: &Element, record: u64) -> Result<(), PlyError> {
        let end = self.pos.saturating_add(bytes);
        if end > self.len {
            return Err(self.truncated(el, record, end));
        }
        let copied = io::copy(&mut (&mut self.reader).take(bytes), &mut io::sink())
            .map_err(|e| self.io("read", e))?;
        if copied < bytes {
            return Err(self.truncated(el, record, end));
        }
        self.pos = end;
        Ok(())
    }

    fn truncated(&self, el: &Element, record: u64, end: u64) -> PlyError {
        PlyError::Truncated {
            path: self.path.clone(),
            element: el.name.clone(),
            record,
            count: el.count,
            end,
            file_len: self.len,
        }
    }

    fn too_many(&self, el: &Element, min_record_bytes: u64, available: u64) -> PlyError {
        PlyError::TooManyRecords {
            path: self.path.clone(),
            element: el.name.clone(),
            count: el.count,
            min_record_bytes,
            offset: self.pos,
            available,
        }
    }

    fn io(&self, action: &'static str, e: io::Error) -> PlyError {
        PlyError::Io {
            path: self.path.clone(),
            action,
            message: e.to_string(),
        }
    }
}

/// One binary value; `b` holds at least `s.size()` bytes.
fn decode(s: Scalar, b: &[u8], big: bool) -> f64 {
    fn bytes<const N: usize>(b: &[u8]) -> [u8; N] {
        let mut a = [0u8; N];
        a.copy_from_slice(&b[..N]);
        a
    }
    macro_rules! get {
        ($t:ty, $n:literal) => {{
            let a = bytes::<$n>(b);
            f64::from(if big {
                <$t>::from_be_bytes(a)
            } else {
                <$t>::from_le_bytes(a)
            })
        }};
    }
    match s {
        Scalar::I8 => get!(i8, 1),
        Scalar::U8 => get!(u8, 1),
        Scalar::I16 => get!(i16, 2),
        Scalar::U16 => get!(u16, 2),
        Scalar::I32 => get!(i32, 4),
        Scalar::U32 => get!(u32, 4),
        Scalar::F32 => get!(f32, 4),
        Scalar::F64 => get!(f64, 8),
    }
}

/// One ASCII record (a line) into `values`; the message says what is wrong.
fn parse_record(text: &str, el: &Element, values: &mut [f64]) -> Result<(), String> {
    let mut tokens = text.split_ascii_whitespace();
    let mut used = 0usize;
    for (v, p) in values.iter_mut().zip(&el.properties) {
        let mut next = |what: &str| {
            let t = tokens.next().ok_or_else(|| {
                format!(
                    "too few values: the line has {used}, {what} of property `{}` is missing",
                    p.name
                )
            })?;
            used += 1;
            Ok::<&str, String>(t)
        };
        match p.kind {
            Kind::Scalar(s) => {
                let t = next("the value")?;
                *v = parse_scalar(t, s).map_err(|m| format!("property `{}`: {m}", p.name))?;
            }
            Kind::List { count, item } => {
                let t = next("the length")?;
                let n = parse_scalar(t, count).map_err(|m| format!("list `{}`: {m}", p.name))?;
                if n < 0.0 {
                    return Err(format!("list `{}`: negative length {n}", p.name));
                }
                for _ in 0..n as u64 {
                    let t = next("an item")?;
                    parse_scalar(t, item).map_err(|m| format!("list `{}`: {m}", p.name))?;
                }
                *v = f64::NAN;
            }
        }
    }
    let extra = tokens.count();
    if extra > 0 {
        return Err(format!(
            "too many values: {extra} left after the {used} the properties take"
        ));
    }
    Ok(())
}

/// One ASCII value of type `s`.
fn parse_scalar(t: &str, s: Scalar) -> Result<f64, String> {
    let bad = || format!("`{t}` is not a valid {}", s.name());
    let int = |lo: i64, hi: i64| {
        t.parse::<i64>()
            .ok()
            .filter(|v| (lo..=hi).contains(v))
            .map(|v| v as f64)
            .ok_or_else(bad)
    };
    match s {
        Scalar::I8 => int(i8::MIN.into(), i8::MAX.into()),
        Scalar::U8 => int(0, u8::MAX.into()),
        Scalar::I16 => int(i16::MIN.into(), i16::MAX.into()),
        Scalar::U16 => int(0, u16::MAX.into()),
        Scalar::I32 => int(i32::MIN.into(), i32::MAX.into()),
        Scalar::U32 => int(0, u32::MAX.into()),
        Scalar::F32 => t.parse::<f32>().map(f64::from).map_err(|_| bad()),
        Scalar::F64 => t.parse::<f64>().map_err(|_| bad()),
    }
}
