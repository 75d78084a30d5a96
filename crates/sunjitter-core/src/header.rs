//! FITS headers without cfitsio: 80-byte cards → typed values, and what a header says about
//! its HDU (kind, image geometry, data size). Pure functions; the file I/O is in sunjitter-io's `fits`.
//!
//! Parsing is tolerant on purpose: real archives hold headers that cfitsio refuses (e.g. TRACE
//! files written by old IDL code with `NAXISn` cards out of order). The structure is checked
//! separately ([`mandatory_order_problem`]) so the reader can warn and carry on.

use serde::{Deserialize, Serialize};

/// Bytes per FITS block.
pub const BLOCK: usize = 2880;
/// Bytes per header card.
pub const CARD: usize = 80;
/// Largest image frame accepted (pixels), 16384²: refuses absurd headers before allocating.
pub const MAX_FRAME_PIXELS: u64 = 1 << 28;
/// Largest length of a single axis accepted.
pub const MAX_AXIS: u64 = 1 << 24;
/// Most frames (planes beyond the second axis) accepted in one image: a day at 1 s cadence
/// fits; a tiny file claiming millions of planes cannot make the reader list them all.
pub const MAX_FRAMES: u64 = 1 << 17;

/// A header keyword's value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum HeaderValue {
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
}

impl HeaderValue {
    /// The value as a finite number; numeric strings (`WAVE_LEN = '171'`) count, `'nan'` does not.
    pub fn as_f64(&self) -> Option<f64> {
        let v = match self {
            HeaderValue::Int(i) => *i as f64,
            HeaderValue::Float(f) => *f,
            HeaderValue::Str(s) => s.trim().parse::<f64>().ok()?,
            HeaderValue::Bool(_) => return None,
        };
        v.is_finite().then_some(v)
    }

    /// The value as an integer (a float with no fractional part counts).
    pub fn as_i64(&self) -> Option<i64> {
        match self {
            HeaderValue::Int(i) => Some(*i),
            HeaderValue::Float(f) if f.fract() == 0.0 && f.abs() < 9.0e15 => Some(*f as i64),
            _ => None,
        }
    }

    pub fn as_str(&self) -> Option<&str> {
        match self {
            HeaderValue::Str(s) => Some(s.as_str()),
            _ => None,
        }
    }
}

impl From<f64> for HeaderValue {
    fn from(v: f64) -> Self {
        HeaderValue::Float(v)
    }
}
impl From<i64> for HeaderValue {
    fn from(v: i64) -> Self {
        HeaderValue::Int(v)
    }
}
impl From<bool> for HeaderValue {
    fn from(v: bool) -> Self {
        HeaderValue::Bool(v)
    }
}
impl From<&str> for HeaderValue {
    fn from(v: &str) -> Self {
        HeaderValue::Str(v.to_string())
    }
}
impl From<String> for HeaderValue {
    fn from(v: String) -> Self {
        HeaderValue::Str(v)
    }
}

/// One header card. `value` is `None` for commentary cards and undefined values.
#[derive(Debug, Clone, PartialEq)]
pub struct Card {
    pub key: String,
    pub value: Option<HeaderValue>,
    pub comment: String,
}

/// The cards of one HDU header, in file order (CONTINUE cards merged into their string).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Header {
    cards: Vec<Card>,
    complete: bool,
}

impl Header {
    pub fn new() -> Self {
        Self::default()
    }

    /// Parse a whole header from bytes (a multiple of 80; stops at `END`).
    pub fn parse(bytes: &[u8]) -> Header {
        let mut header = Header::new();
        for card in bytes.chunks(CARD) {
            if header.push_raw_card(card) {
                break;
            }
        }
        header
    }

    /// Add the cards of one 2880-byte block; returns true once the `END` card has been seen.
    pub fn push_block(&mut self, block: &[u8]) -> bool {
        for card in block.chunks(CARD) {
            if self.push_raw_card(card) {
                return true;
            }
        }
        false
    }

    /// True when an `END` card was seen.
    pub fn is_complete(&self) -> bool {
        self.complete
    }

    fn push_raw_card(&mut self, raw: &[u8]) -> bool {
        if self.complete {
            return true;
        }
        let card = parse_card(raw);
        if card.key == "END" && card.value.is_none() {
            self.complete = true;
            return true;
        }
        if card.key == "CONTINUE" && self.continue_last_string(&card) {
            return false;
        }
        self.cards.push(card);
        false
    }

    /// Long-string convention: `'abc&'` followed by `CONTINUE 'def'` is `'abcdef'`.
    fn continue_last_string(&mut self, card: &Card) -> bool {
        let Some(HeaderValue::Str(more)) = &card.value else {
            return false;
        };
        let Some(Card {
            value: Some(HeaderValue::Str(s)),
            ..
        }) = self.cards.last_mut()
        else {
            return false;
        };
        if !s.ends_with('&') {
            return false;
        }
        s.pop();
        s.push_str(more);
        true
    }

    /// Append a card (for headers built in code).
    pub fn push(&mut self, key: &str, value: HeaderValue) {
        self.cards.push(Card {
            key: key.to_string(),
            value: Some(value),
            comment: String::new(),
        });
    }

    pub fn push_with_comment(&mut self, key: &str, value: HeaderValue, comment: &str) {
        self.cards.push(Card {
            key: key.to_string(),
            value: Some(value),
            comment: comment.to_string(),
        });
    }

    pub fn cards(&self) -> &[Card] {
        &self.cards
    }

    /// Give the first card with this keyword `value` (its comment kept), or append one.
    pub fn set(&mut self, key: &str, value: HeaderValue) {
        match self.cards.iter_mut().find(|c| c.key == key) {
            Some(card) => card.value = Some(value),
            None => self.push(key, value),
        }
    }

    /// Index of the first card with this keyword.
    pub fn position(&self, key: &str) -> Option<usize> {
        self.cards.iter().position(|c| c.key == key)
    }

    /// The value of the first card with this keyword that has one.
    pub fn get(&self, key: &str) -> Option<&HeaderValue> {
        self.cards
            .iter()
            .find(|c| c.key == key)
            .and_then(|c| c.value.as_ref())
    }

    /// The comment of the first card with this keyword.
    pub fn comment(&self, key: &str) -> Option<&str> {
        self.cards
            .iter()
            .find(|c| c.key == key)
            .map(|c| c.comment.trim())
    }

    pub fn contains(&self, key: &str) -> bool {
        self.get(key).is_some()
    }

    /// A finite number (see [`HeaderValue::as_f64`]).
    pub fn f64(&self, key: &str) -> Option<f64> {
        self.get(key).and_then(HeaderValue::as_f64)
    }

    pub fn i64(&self, key: &str) -> Option<i64> {
        self.get(key).and_then(HeaderValue::as_i64)
    }

    /// A string value, trimmed; `None` when absent or blank.
    pub fn str(&self, key: &str) -> Option<&str> {
        let s = self.get(key)?.as_str()?.trim();
        (!s.is_empty()).then_some(s)
    }

    pub fn bool(&self, key: &str) -> Option<bool> {
        match self.get(key)? {
            HeaderValue::Bool(b) => Some(*b),
            _ => None,
        }
    }
}

/// Parse one 80-byte card (shorter input is treated as blank-padded).
pub fn parse_card(raw: &[u8]) -> Card {
    let text: String = raw
        .iter()
        .take(CARD)
        .map(|&b| if b.is_ascii() { b as char } else { '?' })
        .collect();
    let key = text
        .get(..8.min(text.len()))
        .unwrap_or("")
        .trim_end()
        .to_string();
    let rest = text.get(8..).unwrap_or("");
    if key == "HIERARCH" {
        if let Some((name, field)) = rest.split_once('=') {
            let (value, comment) = parse_value_field(field);
            return Card {
                key: name.trim().to_string(),
                value,
                comment,
            };
        }
    }
    let (value, comment) = if rest.starts_with("= ") || (rest.starts_with('=') && rest.len() == 1) {
        parse_value_field(&rest[1..])
    } else if key == "CONTINUE" {
        parse_value_field(rest)
    } else {
        (None, rest.trim_end().to_string())
    };
    Card {
        key,
        value,
        comment,
    }
}

/// Parse the value/comment field after the value indicator.
fn parse_value_field(field: &str) -> (Option<HeaderValue>, String) {
    let field = field.trim_start();
    if let Some(quoted) = field.strip_prefix('\'') {
        let (s, after) = parse_quoted(quoted);
        let comment = after
            .split_once('/')
            .map(|(_, c)| c.trim().to_string())
            .unwrap_or_default();
        return (Some(HeaderValue::Str(s)), comment);
    }
    let (token, comment) = match field.split_once('/') {
        Some((v, c)) => (v.trim(), c.trim().to_string()),
        None => (field.trim(), String::new()),
    };
    (parse_scalar(token), comment)
}

/// A FITS string body after the opening quote: `''` is a quote; trailing blanks do not count.
fn parse_quoted(text: &str) -> (String, &str) {
    let mut out = String::new();
    let mut chars = text.char_indices().peekable();
    while let Some((i, c)) = chars.next() {
        if c == '\'' {
            if matches!(chars.peek(), Some((_, '\''))) {
                out.push('\'');
                chars.next();
                continue;
            }
            return (out.trim_end().to_string(), &text[i + 1..]);
        }
        out.push(c);
    }
    // Unterminated string: keep what there is.
    (out.trim_end().to_string(), "")
}

/// Logical, integer or float (Fortran `D` exponents allowed); complex and junk → `None`.
fn parse_scalar(token: &str) -> Option<HeaderValue> {
    match token {
        "" => None,
        "T" => Some(HeaderValue::Bool(true)),
        "F" => Some(HeaderValue::Bool(false)),
        _ => {
            let digits = token.strip_prefix(['+', '-']).unwrap_or(token);
            if !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit()) {
                if let Ok(i) = token.parse::<i64>() {
                    return Some(HeaderValue::Int(i));
                }
            }
            let normalised = token.replace(['D', 'd'], "E");
            let looks_numeric = normalised
                .bytes()
                .all(|b| b.is_ascii_digit() || b"+-.eE".contains(&b));
            if looks_numeric {
                normalised.parse::<f64>().ok().map(HeaderValue::Float)
            } else {
                None
            }
        }
    }
}

/// What an HDU holds, from its first card.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum HduKind {
    Primary,
    Image,
    BinTable,
    AsciiTable,
    Other(String),
}

/// Image dimensions and pixel type (of the uncompressed image for tile-compressed HDUs).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ImageGeometry {
    pub bitpix: i32,
    /// `NAXIS1`, `NAXIS2`, … (x first).
    pub axes: Vec<usize>,
    /// Tile-compressed (a `ZIMAGE = T` binary table).
    pub compressed: bool,
}

impl ImageGeometry {
    /// `NAXIS1` (0 for a geometry without axes).
    pub fn width(&self) -> usize {
        self.axes.first().copied().unwrap_or(0)
    }

    /// `NAXIS2` (1 for a single row).
    pub fn height(&self) -> usize {
        self.axes.get(1).copied().unwrap_or(1)
    }

    /// Number of 2-D frames (product of the axes beyond the second).
    pub fn frames(&self) -> usize {
        self.axes.iter().skip(2).product()
    }

    /// A 3-D (or higher) array: a stack of frames, even when it holds only one.
    pub fn is_cube(&self) -> bool {
        self.axes.len() >= 3
    }

    pub fn pixels_per_frame(&self) -> usize {
        self.width() * self.height()
    }

    pub fn bytes_per_pixel(&self) -> usize {
        (self.bitpix.unsigned_abs() / 8) as usize
    }
}

/// The HDU kind: `SIMPLE = T` for the primary, `XTENSION` for the others.
pub fn hdu_kind(header: &Header, is_primary: bool) -> Result<HduKind, String> {
    let first = header.cards().first().map(|c| c.key.as_str()).unwrap_or("");
    if is_primary {
        if first != "SIMPLE" {
            return Err("not a FITS file (it does not start with SIMPLE =)".into());
        }
        return match header.bool("SIMPLE") {
            Some(true) => Ok(HduKind::Primary),
            _ => Err("SIMPLE is not T: the file says it does not conform to FITS".into()),
        };
    }
    if first != "XTENSION" {
        return Err("extension header does not start with XTENSION".into());
    }
    Ok(match header.str("XTENSION").unwrap_or("") {
        "IMAGE" => HduKind::Image,
        "BINTABLE" | "A3DTABLE" => HduKind::BinTable,
        "TABLE" => HduKind::AsciiTable,
        other => HduKind::Other(other.to_string()),
    })
}

/// `BITPIX` value check: 8, 16, 32, 64, −32, −64.
fn valid_bitpix(bitpix: i64) -> bool {
    matches!(bitpix, 8 | 16 | 32 | 64 | -32 | -64)
}

/// Axis lengths `{prefix}1..{prefix}n` with `n = {prefix}` (e.g. `NAXIS`, `ZNAXIS`).
fn axes(header: &Header, prefix: &str) -> Result<Vec<u64>, String> {
    let n = header
        .i64(prefix)
        .ok_or_else(|| format!("{prefix} is missing"))?;
    if !(0..=999).contains(&n) {
        return Err(format!("{prefix} = {n} is not between 0 and 999"));
    }
    (1..=n)
        .map(|i| {
            let key = format!("{prefix}{i}");
            match header.i64(&key) {
                Some(v) if v >= 0 => Ok(v as u64),
                Some(v) => Err(format!("{key} = {v} is negative")),
                None => Err(format!("{key} is missing")),
            }
        })
        .collect()
}

/// Size in bytes of the HDU's data (without padding): `|BITPIX|/8 · GCOUNT · (PCOUNT + ΠNAXISn)`.
/// Overflow is an error, so absurd headers cannot wrap around.
pub fn data_size_bytes(header: &Header) -> Result<u64, String> {
    let bitpix = header.i64("BITPIX").ok_or("BITPIX is missing")?;
    if !valid_bitpix(bitpix) {
        return Err(format!("BITPIX = {bitpix} is not a FITS pixel type"));
    }
    let axes = axes(header, "NAXIS")?;
    if axes.is_empty() {
        return Ok(0);
    }
    // Random groups (NAXIS1 = 0 with GROUPS = T) count the axes after the first.
    let counted = if axes[0] == 0 && header.bool("GROUPS") == Some(true) {
        &axes[1..]
    } else {
        &axes[..]
    };
    let too_big = || format!("header claims an absurd data size (NAXISn = {axes:?})");
    let mut elements: u64 = 1;
    for &a in counted {
        elements = elements.checked_mul(a).ok_or_else(too_big)?;
    }
    let pcount = header.i64("PCOUNT").unwrap_or(0).max(0) as u64;
    let gcount = header.i64("GCOUNT").unwrap_or(1).max(0) as u64;
    let bytes_per = bitpix.unsigned_abs() / 8;
    elements
        .checked_add(pcount)
        .and_then(|e| e.checked_mul(gcount))
        .and_then(|e| e.checked_mul(bytes_per))
        .ok_or_else(too_big)
}

/// The image this HDU holds, if any: a primary/IMAGE array with NAXIS ≥ 1, or a
/// tile-compressed image (`ZIMAGE = T`). Refuses absurd sizes (before anything is allocated).
pub fn image_geometry(header: &Header, kind: &HduKind) -> Result<Option<ImageGeometry>, String> {
    let (bitpix_key, prefix, compressed) = match kind {
        HduKind::Primary | HduKind::Image => ("BITPIX", "NAXIS", false),
        HduKind::BinTable if header.bool("ZIMAGE") == Some(true) => ("ZBITPIX", "ZNAXIS", true),
        _ => return Ok(None),
    };
    let bitpix = header
        .i64(bitpix_key)
        .ok_or_else(|| format!("{bitpix_key} is missing"))?;
    if !valid_bitpix(bitpix) {
        return Err(format!("{bitpix_key} = {bitpix} is not a FITS pixel type"));
    }
    let axes = axes(header, prefix)?;
    if axes.len() < 2 || axes.contains(&0) {
        return Ok(None);
    }
    check_sizes(&axes, prefix)?;
    if compressed {
        check_tiles(header, &axes)?;
    } else {
        check_scaling(header)?;
    }
    Ok(Some(ImageGeometry {
        bitpix: bitpix as i32,
        axes: axes.iter().map(|&a| a as usize).collect(),
        compressed,
    }))
}

/// `BSCALE` and `BZERO` (physical = BZERO + BSCALE · stored, FITS standard §5.3) must be finite
/// numbers when present, and `BSCALE` not zero: any other value would silently change every
/// pixel (or be silently ignored).
fn check_scaling(header: &Header) -> Result<(), String> {
    for key in ["BSCALE", "BZERO"] {
        // A card whose value is no FITS value at all (an unquoted `NAN`) counts as present.
        let Some(card) = header.cards().iter().find(|c| c.key == key) else {
            continue;
        };
        let shown = match &card.value {
            None => {
                return Err(format!(
                    "{key} has no value a FITS reader can use (not a finite number)"
                ))
            }
            Some(v) => match v.as_f64() {
                Some(0.0) if key == "BSCALE" => {
                    return Err("BSCALE = 0 would make every pixel BZERO".into())
                }
                Some(_) => continue,
                None => match v {
                    HeaderValue::Str(s) => format!("'{s}'"),
                    HeaderValue::Bool(b) => (if *b { "T" } else { "F" }).to_string(),
                    HeaderValue::Int(i) => i.to_string(),
                    HeaderValue::Float(f) => f.to_string(),
                },
            },
        };
        return Err(format!("{key} = {shown} is not a finite number"));
    }
    Ok(())
}

/// Refuse axes or frames too large to be a real image.
fn check_sizes(axes: &[u64], prefix: &str) -> Result<(), String> {
    if let Some((i, &a)) = axes.iter().enumerate().find(|(_, &a)| a > MAX_AXIS) {
        return Err(format!(
            "absurd image size: {prefix}{} = {a} (limit {MAX_AXIS})",
            i + 1
        ));
    }
    let dims = || {
        let dims: Vec<String> = axes.iter().map(u64::to_string).collect();
        dims.join(" × ")
    };
    let frame = axes[0].saturating_mul(axes.get(1).copied().unwrap_or(1));
    if frame > MAX_FRAME_PIXELS {
        return Err(format!(
            "absurd image size {} (a frame over {MAX_FRAME_PIXELS} pixels)",
            dims()
        ));
    }
    // The planes' product could overflow (tile-compressed images are not bounded by the
    // file's size) or ask for millions of frames.
    let frames = axes.iter().skip(2).try_fold(1u64, |n, &a| n.checked_mul(a));
    if frames.is_none_or(|n| n > MAX_FRAMES) {
        return Err(format!(
            "absurd image size {} (over {MAX_FRAMES} frames)",
            dims()
        ));
    }
    Ok(())
}

/// Compression tiles (`ZTILEn`) larger than the image would make cfitsio allocate for them;
/// and the table must hold one row per tile (the tiled-image convention), which ties the
/// image's claimed size to the file's.
fn check_tiles(header: &Header, axes: &[u64]) -> Result<(), String> {
    let mut tiles: u64 = 1;
    for (i, &axis) in axes.iter().enumerate() {
        let key = format!("ZTILE{}", i + 1);
        // Default tiling: whole rows.
        let tile = header
            .i64(&key)
            .unwrap_or(if i == 0 { axis as i64 } else { 1 });
        if tile < 1 || tile as u64 > axis {
            return Err(format!(
                "{key} = {tile} does not fit ZNAXIS{} = {axis}",
                i + 1
            ));
        }
        tiles = tiles.saturating_mul(axis.div_ceil(tile as u64));
    }
    match header.i64("NAXIS2") {
        Some(rows) if rows >= 0 && rows as u64 == tiles => Ok(()),
        rows => Err(format!(
            "tile-compressed image of {tiles} tiles in a table of {} rows (one row per tile)",
            rows.map_or("no".to_string(), |r| r.to_string())
        )),
    }
}

/// The FITS standard fixes the order of the first cards (`SIMPLE`/`XTENSION`, `BITPIX`,
/// `NAXIS`, `NAXIS1`…`NAXISn`). Describe a violation (cfitsio refuses such files), or `None`.
pub fn mandatory_order_problem(header: &Header) -> Option<String> {
    let n = header.i64("NAXIS").unwrap_or(0).clamp(0, 999) as usize;
    let mut expected = vec!["BITPIX".to_string(), "NAXIS".to_string()];
    expected.extend((1..=n).map(|i| format!("NAXIS{i}")));
    let misplaced: Vec<String> = expected
        .iter()
        .enumerate()
        .filter_map(|(i, key)| match header.position(key) {
            Some(pos) if pos == i + 1 => None,
            Some(pos) => Some(format!("{key} is card {} (should be {})", pos + 1, i + 2)),
            None => Some(format!("{key} is missing")),
        })
        .collect();
    (!misplaced.is_empty())
        .then(|| format!("mandatory cards out of order: {}", misplaced.join(", ")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn card(text: &str) -> Vec<u8> {
        format!("{text:<80}").into_bytes()
    }

    fn header(cards: &[&str]) -> Header {
        let mut bytes: Vec<u8> = cards.iter().flat_map(|c| card(c)).collect();
        bytes.extend(card("END"));
        Header::parse(&bytes)
    }

    #[test]
    fn parses_fixed_and_free_format_values() {
        let h = header(&[
            "SIMPLE  =                    T / conforms to FITS standard",
            "BITPIX  =                  -64 / array data type",
            "CDELT1  =            19.183648",
            "EXPO    =              1.5D+01 / Fortran exponent",
            "OBJECT  = 'O''Hara  '           / quote inside",
            "WAVE_LEN= '171     '",
            "OSCNMEAN= 'nan     '",
            "EMPTY   =                      / undefined value",
            "COMMENT   CORRECTED DATE_OBS = '2004-02-29T23:58:20.443Z'",
            "HIERARCH ESO DET DIT = 2.5 / hierarchical",
        ]);
        assert_eq!(h.bool("SIMPLE"), Some(true));
        assert_eq!(h.i64("BITPIX"), Some(-64));
        assert_eq!(h.f64("CDELT1"), Some(19.183648));
        assert_eq!(h.f64("EXPO"), Some(15.0));
        assert_eq!(h.str("OBJECT"), Some("O'Hara"));
        assert_eq!(h.f64("WAVE_LEN"), Some(171.0));
        assert_eq!(h.f64("OSCNMEAN"), None);
        assert_eq!(h.get("EMPTY"), None);
        // Commentary cards carry no value, even when they look like one.
        assert_eq!(h.get("COMMENT"), None);
        assert_eq!(h.f64("ESO DET DIT"), Some(2.5));
        assert!(h.is_complete());
    }

    #[test]
    fn merges_continue_cards() {
        let h = header(&[
            "SOURCE  = 'hmi.lev1[:#158263685,&'",
            "CONTINUE  '#158&'",
            "CONTINUE  'end'",
        ]);
        assert_eq!(h.str("SOURCE"), Some("hmi.lev1[:#158263685,#158end"));
    }

    #[test]
    fn data_size_and_geometry() {
        let h = header(&[
            "SIMPLE  = T",
            "BITPIX  = 16",
            "NAXIS   = 3",
            "NAXIS1  = 110",
            "NAXIS2  = 109",
            "NAXIS3  = 54",
        ]);
        assert_eq!(data_size_bytes(&h).unwrap(), 2 * 110 * 109 * 54);
        let g = image_geometry(&h, &HduKind::Primary).unwrap().unwrap();
        assert_eq!(
            (g.width(), g.height(), g.frames(), g.is_cube()),
            (110, 109, 54, true)
        );
        assert_eq!(mandatory_order_problem(&h), None);
    }

    #[test]
    fn refuses_absurd_sizes_without_overflow() {
        let h = header(&[
            "SIMPLE  = T",
            "BITPIX  = 16",
            "NAXIS   = 2",
            "NAXIS1  = 2000000000",
            "NAXIS2  = 1",
        ]);
        let e = image_geometry(&h, &HduKind::Primary).unwrap_err();
        assert!(e.contains("NAXIS1 = 2000000000"), "{e}");
        let huge = header(&[
            "SIMPLE  = T",
            "BITPIX  = -64",
            "NAXIS   = 3",
            "NAXIS1  = 9223372036854775807",
            "NAXIS2  = 9223372036854775807",
            "NAXIS3  = 4",
        ]);
        assert!(data_size_bytes(&huge).unwrap_err().contains("absurd"));
        // Planes: a tiny tile-compressed table claiming 2⁷² planes would overflow the frame
        // count; 2²⁴ would list 16 M frames.
        for planes in [
            &[
                "ZNAXIS3 = 16777216",
                "ZNAXIS4 = 16777216",
                "ZNAXIS5 = 16777216",
            ][..],
            &["ZNAXIS3 = 16777216"][..],
        ] {
            let mut cards = vec![
                "XTENSION= 'BINTABLE'".to_string(),
                "NAXIS   = 2".into(),
                "NAXIS1  = 8".into(),
                "NAXIS2  = 2".into(),
                "ZIMAGE  = T".into(),
                "ZBITPIX = 16".into(),
                format!("ZNAXIS  = {}", 2 + planes.len()),
                "ZNAXIS1 = 2".into(),
                "ZNAXIS2 = 2".into(),
            ];
            cards.extend(planes.iter().map(|p| p.to_string()));
            let refs: Vec<&str> = cards.iter().map(String::as_str).collect();
            let e = image_geometry(&header(&refs), &HduKind::BinTable).unwrap_err();
            assert!(e.contains("frames"), "{e}");
        }
        let many = header(&[
            "SIMPLE  = T",
            "BITPIX  = 8",
            "NAXIS   = 3",
            "NAXIS1  = 1",
            "NAXIS2  = 1",
            "NAXIS3  = 16777216",
        ]);
        let e = image_geometry(&many, &HduKind::Primary).unwrap_err();
        assert!(e.contains("over 131072 frames"), "{e}");
    }

    #[test]
    fn compressed_geometry_and_tile_check() {
        let ok = header(&[
            "XTENSION= 'BINTABLE'",
            "BITPIX  = 8",
            "NAXIS   = 2",
            "NAXIS1  = 8",
            "NAXIS2  = 16",
            "ZIMAGE  = T",
            "ZBITPIX = 16",
            "ZNAXIS  = 2",
            "ZNAXIS1 = 64",
            "ZNAXIS2 = 16",
            "ZTILE1  = 64",
            "ZTILE2  = 1",
        ]);
        let g = image_geometry(&ok, &HduKind::BinTable).unwrap().unwrap();
        assert_eq!(
            (g.bitpix, g.axes.clone(), g.compressed),
            (16, vec![64, 16], true)
        );
        let bad = header(&[
            "XTENSION= 'BINTABLE'",
            "BITPIX  = 8",
            "NAXIS   = 2",
            "NAXIS1  = 8",
            "NAXIS2  = 16",
            "ZIMAGE  = T",
            "ZBITPIX = 16",
            "ZNAXIS  = 2",
            "ZNAXIS1 = 64",
            "ZNAXIS2 = 16",
            "ZTILE1  = 2000000000",
        ]);
        assert!(image_geometry(&bad, &HduKind::BinTable)
            .unwrap_err()
            .contains("ZTILE1"));
        // One row per tile: 64 × 16 in 16 × 4 tiles is 4 × 4 = 16 rows, not 15.
        let tiles = |rows: &str| {
            header(&[
                "XTENSION= 'BINTABLE'",
                "BITPIX  = 8",
                "NAXIS   = 2",
                "NAXIS1  = 8",
                rows,
                "ZIMAGE  = T",
                "ZBITPIX = 16",
                "ZNAXIS  = 2",
                "ZNAXIS1 = 64",
                "ZNAXIS2 = 16",
                "ZTILE1  = 16",
                "ZTILE2  = 4",
            ])
        };
        assert!(image_geometry(&tiles("NAXIS2  = 16"), &HduKind::BinTable).is_ok());
        let e = image_geometry(&tiles("NAXIS2  = 15"), &HduKind::BinTable).unwrap_err();
        assert!(e.contains("16 tiles in a table of 15 rows"), "{e}");
        // A plain binary table holds no image.
        let table = header(&[
            "XTENSION= 'BINTABLE'",
            "BITPIX  = 8",
            "NAXIS   = 2",
            "NAXIS1  = 8",
            "NAXIS2  = 16",
        ]);
        assert_eq!(image_geometry(&table, &HduKind::BinTable).unwrap(), None);
    }

    #[test]
    fn reports_out_of_order_naxis_cards() {
        let h = header(&[
            "SIMPLE  = T",
            "BITPIX  = 16",
            "NAXIS   = 2",
            "DATE    = 'x'",
            "NAXIS1  = 4",
            "NAXIS2  = 4",
        ]);
        let p = mandatory_order_problem(&h).unwrap();
        assert!(
            p.contains("NAXIS1 is card 5 (should be 4)")
                && p.contains("NAXIS2 is card 6 (should be 5)"),
            "{p}"
        );
        // The values are still readable.
        assert_eq!(
            image_geometry(&h, &HduKind::Primary).unwrap().unwrap().axes,
            vec![4, 4]
        );
    }

    #[test]
    fn non_fits_first_card_is_an_error() {
        let h = Header::parse(&card("<!DOCTYPE HTML PUBLIC"));
        assert!(hdu_kind(&h, true).unwrap_err().contains("not a FITS file"));
        assert!(!h.is_complete());
    }
}
