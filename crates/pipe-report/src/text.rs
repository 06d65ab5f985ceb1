//! Number and text formatting shared by the HTML and Markdown writers.

use serde_json::Value;

/// A number for a table: 4 significant digits, scientific outside [1e-3, 1e5).
pub fn num(v: f64) -> String {
    if !v.is_finite() {
        return if v.is_nan() {
            "NaN".into()
        } else {
            format!("{v}")
        };
    }
    let a = v.abs();
    if a != 0.0 && !(1e-3..1e5).contains(&a) {
        format!("{v:.3e}")
    } else if a >= 100.0 {
        format!("{v:.1}")
    } else if a >= 10.0 {
        format!("{v:.2}")
    } else if a >= 1.0 {
        format!("{v:.3}")
    } else {
        format!("{v:.4}")
    }
}

/// A text, `—` when empty.
pub fn or_dash(s: &str) -> String {
    if s.is_empty() { "—".into() } else { s.into() }
}

/// An optional number, `—` when absent.
pub fn opt(v: Option<f64>) -> String {
    v.map(num).unwrap_or_else(|| "—".into())
}

/// A JSON value for a table: numbers formatted, arrays as `[a, b, c]`, null as `—`.
pub fn value(v: &Value) -> String {
    match v {
        Value::Null => "—".into(),
        Value::Number(n) if n.is_i64() || n.is_u64() => n.to_string(),
        Value::Number(n) => n.as_f64().map(num).unwrap_or_else(|| n.to_string()),
        Value::Array(a) => format!("[{}]", a.iter().map(value).collect::<Vec<_>>().join(", ")),
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// Seconds for a table.
pub fn seconds(v: Option<f64>) -> String {
    v.map(|s| format!("{s:.2}")).unwrap_or_else(|| "—".into())
}

/// Bytes as MiB, `—` when unknown (0 or absent).
pub fn mib(v: Option<u64>) -> String {
    match v {
        Some(b) if b > 0 => format!("{:.0}", b as f64 / (1024.0 * 1024.0)),
        _ => "—".into(),
    }
}

/// A JSON object on one line with `key: value` pairs (parameters in tables).
pub fn compact(v: &Value) -> String {
    match v {
        Value::Object(m) => m
            .iter()
            .map(|(k, v)| format!("{k}: {}", compact(v)))
            .collect::<Vec<_>>()
            .join(", "),
        Value::Array(a) => format!("[{}]", a.iter().map(compact).collect::<Vec<_>>().join(", ")),
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// HTML-escape text (element content and attribute values).
pub fn html(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// Escape a Markdown table cell.
pub fn md(s: &str) -> String {
    s.replace('|', "\\|").replace('\n', " ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_keep_four_significant_digits() {
        assert_eq!(num(1.0e6), "1.000e6");
        assert_eq!(num(0.3), "0.3000");
        assert_eq!(num(32.93), "32.93");
        assert_eq!(num(0.00697), "0.0070");
        assert_eq!(num(0.0001), "1.000e-4");
        assert_eq!(num(f64::NAN), "NaN");
        assert_eq!(
            html("<a href=\"x\">&'"),
            "&lt;a href=&quot;x&quot;&gt;&amp;&#39;"
        );
        assert_eq!(
            value(&serde_json::json!([0.15, -0.3, null, 10])),
            "[0.1500, -0.3000, —, 10]"
        );
    }
}
