//! A check of a CDF file's structure before the `cdf` crate (0.1.4) decodes it.
//!
//! The crate sizes buffers from counts and sizes it reads from the file before it reads what they
//! describe: `vec![0u8; CSize]` for a CVVR, `vec![0u8; RecordSize - 28]` for a UIR,
//! `vec![None; NumEntries]` for a VXR, and `Vec::with_capacity` for the GDR's rDimSizes, a zVDR's
//! zDimSizes and DimVarys, a VDR's pad value and an attribute entry's value (NumElems), a VVR's records
//! (Last - First + 1 of its VXR entry) and each record's values (NumElems times the varying dimension
//! sizes). A file declaring petabytes makes it abort the process: an allocation failure is not a panic
//! that `catch_unwind` can catch. It also follows links without remembering them, so a link back loops
//! forever (a chain) or overflows the stack (the index tree), and a record linked twice is decoded twice.
//!
//! [`check`] reads the same records in the same order, with the same field widths (4-byte sizes and
//! offsets before CDF 3.0, 8-byte from 3.0 on), and refuses a file unless every record it reaches lies
//! within the file, is reached once and holds each array the decoder reads from it. The bytes read into
//! buffers over the whole file may not exceed its length either, so that overlapping records cannot
//! multiply them. The decoder reads no CCR, CPR or SPR (compressed files and sparse records), nor does this.
use std::collections::HashSet;

/// Most levels of variable index records (VXRs) the decoder may recurse through, a few stack frames
/// each. Real files have a few levels: at 7 entries a record, 32 levels would index 7^32 blocks.
pub const MAX_INDEX_DEPTH: usize = 32;

/// The advice for a file compressed as a whole, which the decoder cannot read.
const COMPRESSED: &str = "the whole file is compressed; decompress it first (CDF tools: `cdfconvert -compression cdf:none`)";

/// The internal records the decoder reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Cdr,
    Gdr,
    RVdr,
    Adr,
    AgrEdr,
    Vxr,
    Vvr,
    ZVdr,
    AzEdr,
    Cvvr,
    Uir,
}

impl Kind {
    /// The RecordType field of the CDF specification.
    fn code(self) -> i32 {
        match self {
            Kind::Cdr => 1,
            Kind::Gdr => 2,
            Kind::RVdr => 3,
            Kind::Adr => 4,
            Kind::AgrEdr => 5,
            Kind::Vxr => 6,
            Kind::Vvr => 7,
            Kind::ZVdr => 8,
            Kind::AzEdr => 9,
            Kind::Cvvr => 13,
            Kind::Uir => -1,
        }
    }

    /// The name with its article, as in "an ADR".
    fn name(self) -> &'static str {
        match self {
            Kind::Cdr => "a CDR",
            Kind::Gdr => "a GDR",
            Kind::RVdr => "an rVDR",
            Kind::Adr => "an ADR",
            Kind::AgrEdr => "an AgrEDR",
            Kind::Vxr => "a VXR",
            Kind::Vvr => "a VVR",
            Kind::ZVdr => "a zVDR",
            Kind::AzEdr => "an AzEDR",
            Kind::Cvvr => "a CVVR",
            Kind::Uir => "a UIR",
        }
    }

    /// The field that links a record to the next of its chain, the first after RecordType.
    fn next_field(self) -> &'static str {
        match self {
            Kind::RVdr | Kind::ZVdr => "VDRnext",
            Kind::Adr => "ADRnext",
            Kind::AgrEdr | Kind::AzEdr => "AEDRnext",
            Kind::Vxr => "VXRnext",
            Kind::Uir => "NextUIR",
            _ => "link",
        }
    }
}

/// Bytes per value of a CDF data type as the decoder reads them; `None` for a code it refuses.
fn type_width(data_type: i32) -> Option<u64> {
    match data_type {
        1 | 11 | 41 | 51 | 52 => Some(1),
        2 | 12 => Some(2),
        4 | 14 | 21 | 44 => Some(4),
        8 | 22 | 31 | 33 | 45 => Some(8),
        32 => Some(16),
        _ => None,
    }
}

/// `N` bytes of `bytes` from `at`, if the file has them.
fn bytes_at<const N: usize>(bytes: &[u8], at: u64) -> Option<[u8; N]> {
    let from = usize::try_from(at).ok()?;
    bytes.get(from..from.checked_add(N)?)?.try_into().ok()
}

/// A CDF version as (version, release, increment).
type Version = (i32, i32, i32);

/// What one variable's records hold, for its VVRs.
#[derive(Clone, Copy)]
struct Values {
    /// NumElems times the varying dimension sizes, as the decoder computes it.
    per_record: i32,
    /// Bytes per value.
    width: u64,
}

/// One record's fields, read in order as the decoder reads them, within the record's RecordSize.
struct Fields<'a> {
    bytes: &'a [u8],
    /// Sizes and offsets are 8 bytes wide from CDF 3.0 on, 4 before.
    wide: bool,
    kind: Kind,
    start: u64,
    end: u64,
    at: u64,
}

impl<'a> Fields<'a> {
    /// The record, for messages: "a VXR at byte 4624".
    fn what(&self) -> String {
        format!("{} at byte {}", self.kind.name(), self.start)
    }

    fn too_small(&self, to: u64) -> String {
        format!(
            "{} declares RecordSize {}, too small for the fields the decoder reads from it (to byte {to})",
            self.what(),
            self.end - self.start
        )
    }

    fn read<const N: usize>(&mut self) -> Result<[u8; N], String> {
        let to = self.at + N as u64;
        let got = if to <= self.end {
            bytes_at(self.bytes, self.at)
        } else {
            None
        };
        let b = got.ok_or_else(|| self.too_small(to))?;
        self.at = to;
        Ok(b)
    }

    fn int4(&mut self) -> Result<i32, String> {
        self.read().map(i32::from_be_bytes)
    }

    /// A size or file offset: an Int8 from CDF 3.0 on, an Int4 before.
    fn offset(&mut self) -> Result<i64, String> {
        if self.wide {
            self.read().map(i64::from_be_bytes)
        } else {
            self.read().map(|b| i64::from(i32::from_be_bytes(b)))
        }
    }

    fn skip(&mut self, n: u64) -> Result<(), String> {
        let to = self.at + n;
        if to > self.end {
            return Err(self.too_small(to));
        }
        self.at = to;
        Ok(())
    }

    /// `n` Int4s; callers have checked with [`Fields::in_record`] that the record holds them.
    fn int4s(&mut self, n: usize) -> Result<Vec<i32>, String> {
        (0..n).map(|_| self.int4()).collect()
    }

    fn offsets(&mut self, n: usize) -> Result<Vec<i64>, String> {
        (0..n).map(|_| self.offset()).collect()
    }

    /// The bytes of `count` items of `width` bytes from here, which the decoder allocates for: refused
    /// when negative or past `limit` (`scope` names it in the message).
    fn room(
        &self,
        field: &str,
        count: i64,
        width: u64,
        limit: u64,
        scope: &str,
    ) -> Result<u64, String> {
        let n = u64::try_from(count)
            .map_err(|_| format!("{}: {field} {count} is a negative count", self.what()))?;
        let left = limit.saturating_sub(self.at);
        let need = u128::from(n) * u128::from(width);
        u64::try_from(need).ok().filter(|&b| b <= left).ok_or_else(|| {
            format!(
                "{}: {field} {count} asks for {need} bytes, more than the {left} left in {scope}",
                self.what()
            )
        })
    }

    fn in_record(&self, field: &str, count: i64, width: u64) -> Result<u64, String> {
        self.room(field, count, width, self.end, "the record")
    }

    fn in_file(&self, field: &str, count: i64, width: u64) -> Result<u64, String> {
        self.room(field, count, width, self.bytes.len() as u64, "the file")
    }
}

/// The walk over a file's records.
struct Walk<'a> {
    bytes: &'a [u8],
    wide: bool,
    /// Records reached: the decoder remembers none, so a second visit means a loop or a shared record.
    seen: HashSet<u64>,
    /// Bytes the decoder reads into buffers so far.
    claimed: u64,
}

/// Refuses `bytes` unless the `cdf` crate can decode them without allocating more than the file holds,
/// looping or recursing without end; the message names the record, the field and its value.
pub(super) fn check(bytes: &[u8]) -> Result<(), String> {
    let wide = magic(bytes)?;
    let mut walk = Walk {
        bytes,
        wide,
        seen: HashSet::new(),
        claimed: 0,
    };
    let (version, gdr) = walk.cdr()?;
    // The decoder reads the CDR with the width the magic number implies, the rest with its Version's.
    walk.wide = version.0 >= 3;
    walk.gdr(gdr, version)
}

/// Whether sizes and offsets in the CDR are 8 bytes wide, from the magic numbers the decoder knows.
fn magic(bytes: &[u8]) -> Result<bool, String> {
    let word = |at| bytes_at(bytes, at).map(u32::from_be_bytes);
    let wide = match word(0) {
        Some(0xcdf3_0001) => true,
        Some(0xcdf2_6002 | 0x0000_ffff) => false,
        _ => return Err("not a CDF file (its first 4 bytes are not a CDF magic number)".into()),
    };
    match word(4) {
        Some(0x0000_ffff) => Ok(wide),
        Some(0xcccc_0001) => Err(COMPRESSED.into()),
        _ => Err("not a CDF file (bytes 4 to 7 are not a CDF magic number)".into()),
    }
}

impl<'a> Walk<'a> {
    fn len(&self) -> u64 {
        self.bytes.len() as u64
    }

    /// The record at `at`, reached through `link` (for messages), of one of `kinds`: its fields after
    /// RecordType. Refuses a record outside the file, reached before, of another kind, or whose RecordSize
    /// is negative, smaller than its header or past the end of the file.
    fn open(&mut self, at: u64, link: &str, kinds: &[Kind]) -> Result<Fields<'a>, String> {
        let len = self.len();
        let head = if self.wide { 12 } else { 8 };
        if !self.seen.insert(at) {
            return Err(format!(
                "{link} points back to byte {at}, a record the decoder has read already: it would loop or read it twice"
            ));
        }
        let size = if self.wide {
            bytes_at(self.bytes, at).map(i64::from_be_bytes)
        } else {
            bytes_at(self.bytes, at).map(|b| i64::from(i32::from_be_bytes(b)))
        };
        let code = bytes_at(self.bytes, at + head - 4).map(i32::from_be_bytes);
        let (Some(size), Some(code)) = (size, code) else {
            return Err(format!(
                "{link} points to byte {at}, too near the end of the {len}-byte file for a record"
            ));
        };
        let names: Vec<&str> = kinds.iter().map(|k| k.name()).collect();
        let kind = kinds
            .iter()
            .copied()
            .find(|k| k.code() == code)
            .ok_or_else(|| {
                format!(
                    "{link} points to byte {at}, a record of type {code}, not {}",
                    names.join(" or ")
                )
            })?;
        let left = len - at;
        let what = format!("{} at byte {at}", kind.name());
        let end = match u64::try_from(size) {
            Err(_) => {
                return Err(format!(
                    "{what} declares RecordSize {size}, a negative size"
                ));
            }
            Ok(s) if s > left => {
                return Err(format!(
                    "{what} declares RecordSize {size}, more than the {left} bytes from there to the end of the file"
                ));
            }
            Ok(s) if s < head => {
                return Err(format!(
                    "{what} declares RecordSize {size}, less than its {head}-byte header"
                ));
            }
            Ok(s) => at + s,
        };
        Ok(Fields {
            bytes: self.bytes,
            wide: self.wide,
            kind,
            start: at,
            end,
            at: at + head,
        })
    }

    /// [`Walk::open`] for a link read from the file: negative offsets and offsets past the end are refused.
    fn follow(&mut self, at: i64, link: &str, kinds: &[Kind]) -> Result<Fields<'a>, String> {
        match u64::try_from(at) {
            Ok(start) if start < self.len() => self.open(start, link, kinds),
            _ => Err(format!(
                "{link} points to byte {at}, outside the file's {} bytes",
                self.len()
            )),
        }
    }

    /// Counts `bytes` more that the decoder reads into buffers. Records that hold what they declare and
    /// do not overlap hold at most the file's length in all; past it, overlapping records would have the
    /// decoder read the same bytes many times over.
    fn claim(&mut self, bytes: u64) -> Result<(), String> {
        self.claimed = self.claimed.saturating_add(bytes);
        if self.claimed > self.len() {
            return Err(format!(
                "the records declare {} bytes of arrays and values in all, more than the file's {} bytes: they overlap",
                self.claimed,
                self.len()
            ));
        }
        Ok(())
    }

    /// The records of a chain of `kind` from `head` until a link of 0, as the decoder follows them: `body`
    /// checks each past its link to the next.
    fn chain(
        &mut self,
        head: i64,
        link: String,
        kind: Kind,
        mut body: impl FnMut(&mut Self, Fields<'a>) -> Result<(), String>,
    ) -> Result<(), String> {
        let (mut at, mut link) = (head, link);
        while at != 0 {
            let mut f = self.follow(at, &link, &[kind])?;
            at = f.offset()?;
            link = format!("the {} of {}", kind.next_field(), f.what());
            body(self, f)?;
        }
        Ok(())
    }

    /// The CDR: the CDF version it declares and where the decoder reads the GDR, straight after the
    /// CDR's fields (not at GDRoffset).
    fn cdr(&mut self) -> Result<(Version, u64), String> {
        let mut f = self.open(8, "the record after the magic numbers", &[Kind::Cdr])?;
        f.offset()?; // GDRoffset
        let (version, release) = (f.int4()?, f.int4()?);
        f.skip(16)?; // Encoding, Flags, rfuA, rfuB
        let increment = f.int4()?;
        f.skip(8)?; // Identifier, rfuE
        let v = (version, release, increment);
        if [version, release, increment]
            .iter()
            .any(|&x| u16::try_from(x).is_err())
        {
            return Err(format!(
                "{} declares version {version}.{release}.{increment}",
                f.what()
            ));
        }
        f.skip(if v < (2, 5, 0) { 1945 } else { 256 })?; // Copyright
        Ok((v, f.at))
    }

    /// The GDR and the chains it heads, in the decoder's order.
    fn gdr(&mut self, at: u64, version: Version) -> Result<(), String> {
        let mut f = self.open(at, "the record after the CDR", &[Kind::Gdr])?;
        let (rvdr, zvdr, adr) = (f.offset()?, f.offset()?, f.offset()?);
        f.offset()?; // eof
        f.skip(12)?; // rNumVars, NumAttr, rMaxRec
        let r_num_dims = f.int4()?;
        f.skip(4)?; // zNumVars
        let uir = f.offset()?;
        f.skip(12)?; // rfuC, LeapSecondLastUpdated, rfuE
        let n = f.in_record("rNumDims", r_num_dims.into(), 4)?;
        self.claim(n)?;
        let r_dims = f.int4s(n as usize / 4)?;
        let link = |name: &str| format!("the {name} of {}", f.what());
        self.chain(rvdr, link("rVDRhead"), Kind::RVdr, |w, f| {
            w.vdr(f, Some(&r_dims))
        })?;
        // Before CDF 2.2 there were no zVariables: the decoder ignores the field.
        if version >= (2, 2, 0) {
            self.chain(zvdr, link("zVDRhead"), Kind::ZVdr, |w, f| w.vdr(f, None))?;
        }
        self.chain(adr, link("ADRhead"), Kind::Adr, |w, f| w.adr(f, version))?;
        self.chain(uir, link("UIRhead"), Kind::Uir, Self::uir)
    }

    /// A zVDR, or an rVDR with the GDR's rDimSizes: its dimensions, pad value and index tree.
    fn vdr(&mut self, mut f: Fields<'a>, r_dims: Option<&[i32]>) -> Result<(), String> {
        let data_type = f.int4()?;
        f.skip(4)?; // MaxRec
        let vxr_head = f.offset()?;
        f.offset()?; // VXRtail
        f.skip(20)?; // Flags, SRecords, rfuB, rfuC, rfuF
        let num_elems = f.int4()?;
        f.skip(4)?; // Num
        f.offset()?; // CPRorSPRoffset
        f.skip(4 + 256)?; // BlockingFactor, Name
        let (dims, varys) = self.dims(&mut f, r_dims)?;
        let width = type_width(data_type).ok_or_else(|| {
            format!(
                "{} declares DataType {data_type}, not a CDF data type",
                f.what()
            )
        })?;
        // The decoder reads a pad value whether or not Flags says there is one, into the next record if
        // there is not: it has to end within the file.
        self.claim(f.in_file("NumElems (of the pad value)", num_elems.into(), width)?)?;
        let values = Values {
            per_record: per_record(&f, num_elems, &dims, &varys)?,
            width,
        };
        let link = format!("the VXRhead of {}", f.what());
        self.chain(vxr_head, link, Kind::Vxr, |w, f| w.vxr(f, 1, values))
    }

    /// A VDR's dimension sizes (a zVDR's own, or the GDR's for an rVDR) and DimVarys.
    fn dims(
        &mut self,
        f: &mut Fields<'a>,
        r_dims: Option<&[i32]>,
    ) -> Result<(Vec<i32>, Vec<i32>), String> {
        let sizes = match r_dims {
            Some(r) => {
                let n = i64::try_from(r.len()).unwrap_or(i64::MAX);
                self.claim(f.in_record("DimVarys of the GDR's rNumDims", n, 4)?)?;
                r.to_vec()
            }
            None => {
                let n = f.int4()?;
                // zDimSizes and DimVarys, 4 bytes each.
                let bytes = f.in_record("zNumDims", n.into(), 8)?;
                self.claim(bytes)?;
                f.int4s(bytes as usize / 8)?
            }
        };
        let varys = f.int4s(sizes.len())?;
        Ok((sizes, varys))
    }

    /// A VXR `depth` levels down its variable's index tree: its entries and the records they point to.
    fn vxr(&mut self, mut f: Fields<'a>, depth: usize, values: Values) -> Result<(), String> {
        let n = f.int4()?;
        f.skip(4)?; // NusedEntries
        // First and Last (Int4s) and Offset for each entry.
        let entry = if self.wide { 16 } else { 12 };
        let bytes = f.in_record("NumEntries", n.into(), entry)?;
        self.claim(bytes)?;
        let n = (bytes / entry) as usize;
        let (first, last, offsets) = (f.int4s(n)?, f.int4s(n)?, f.offsets(n)?);
        for (i, ((&first, &last), &at)) in first.iter().zip(&last).zip(&offsets).enumerate() {
            // The decoder skips entries whose Offset is -1.
            if at != -1 {
                let entry = format!("entry {i} of {}", f.what());
                self.child(at, &entry, depth, values, (first, last))?;
            }
        }
        Ok(())
    }

    /// The record VXR `entry` points to, holding records `range` (First, Last) of its variable.
    fn child(
        &mut self,
        at: i64,
        entry: &str,
        depth: usize,
        values: Values,
        range: (i32, i32),
    ) -> Result<(), String> {
        let link = format!("the Offset of {entry}");
        let mut f = self.follow(at, &link, &[Kind::Vxr, Kind::Vvr, Kind::Cvvr])?;
        let records = entry_records(entry, range)?;
        match f.kind {
            Kind::Vxr if depth >= MAX_INDEX_DEPTH => Err(format!(
                "{link} points to {}, more than {MAX_INDEX_DEPTH} levels down its variable's index tree",
                f.what()
            )),
            Kind::Vxr => {
                f.offset()?; // VXRnext, which the decoder follows only at the top level
                self.vxr(f, depth + 1, values)
            }
            Kind::Cvvr => {
                f.skip(4)?; // rfuA
                let size = f.offset()?;
                self.claim(f.in_record("CSize", size, 1)?)
            }
            // The kind left: a VVR.
            _ => self.vvr(&f, values, records, entry, range),
        }
    }

    /// A VVR of `records` records: the decoder reserves a slot for each, then reads its values.
    fn vvr(
        &mut self,
        f: &Fields<'a>,
        values: Values,
        records: u64,
        entry: &str,
        range: (i32, i32),
    ) -> Result<(), String> {
        if records == 0 {
            return Ok(());
        }
        let per = u64::try_from(values.per_record).map_err(|_| {
            format!(
                "{}: its variable's NumElems times varying dimension sizes is {}, a negative count",
                f.what(),
                values.per_record
            )
        })?;
        // A record of no values still takes a slot: a byte each bounds their number too.
        let need = u128::from(records) * u128::from((per * values.width).max(1));
        let left = f.end - f.at;
        if need > u128::from(left) {
            return Err(format!(
                "{}: {entry} has First {} and Last {}, {records} records of {per} values (NumElems times varying \
                 dimension sizes) of {} bytes: {need} bytes, more than the {left} left in the record",
                f.what(),
                range.0,
                range.1,
                values.width
            ));
        }
        self.claim(need as u64)
    }

    /// An ADR and its entry chains.
    fn adr(&mut self, mut f: Fields<'a>, version: Version) -> Result<(), String> {
        let agr = f.offset()?;
        f.skip(20)?; // Scope, Num, NgrEntries, MAXgrEntry, rfuA
        let az = f.offset()?;
        f.skip(12)?; // NzEntries, MAXzEntry, rfuE
        f.skip(if version.0 < 3 { 64 } else { 256 })?; // Name
        let (agr_link, az_link) = (
            format!("the AgrEDRhead of {}", f.what()),
            format!("the AzEDRhead of {}", f.what()),
        );
        self.chain(agr, agr_link, Kind::AgrEdr, Self::aedr)?;
        self.chain(az, az_link, Kind::AzEdr, Self::aedr)
    }

    /// An attribute entry (AgrEDR or AzEDR): its value of NumElems items.
    fn aedr(&mut self, mut f: Fields<'a>) -> Result<(), String> {
        f.skip(4)?; // AttrNum
        let data_type = f.int4()?;
        f.skip(4)?; // Num
        let num_elems = f.int4()?;
        f.skip(20)?; // NumStrings, rfuB, rfuC, rfuD, rfuE
        let width = type_width(data_type).ok_or_else(|| {
            format!(
                "{} declares DataType {data_type}, not a CDF data type",
                f.what()
            )
        })?;
        self.claim(f.in_record("NumElems", num_elems.into(), width)?)
    }

    /// A UIR: the decoder reads the rest of the record, RecordSize less its fields.
    fn uir(&mut self, mut f: Fields<'a>) -> Result<(), String> {
        f.offset()?; // PrevUIR
        self.claim(f.end - f.at)
    }
}

/// Values per record of a variable as the decoder computes them: the product of the varying dimension
/// sizes, times NumElems, in 32-bit arithmetic, where an overflow panics or wraps into a wrong count.
fn per_record(f: &Fields, num_elems: i32, dims: &[i32], varys: &[i32]) -> Result<i32, String> {
    dims.iter()
        .zip(varys)
        .filter(|(_, v)| **v == -1)
        .try_fold(1i32, |p, (d, _)| p.checked_mul(*d))
        .and_then(|p| num_elems.checked_mul(p))
        .ok_or_else(|| {
            format!(
                "{}: NumElems {num_elems} times the varying dimension sizes of {dims:?} overflows the decoder's 32-bit count",
                f.what()
            )
        })
}

/// Records of a VXR entry as the decoder counts them, Last - First + 1 in 32-bit arithmetic; -1 is unset.
fn entry_records(entry: &str, (first, last): (i32, i32)) -> Result<u64, String> {
    let n = if first == -1 || last == -1 {
        None
    } else {
        last.checked_sub(first).and_then(|d| d.checked_add(1))
    };
    n.and_then(|n| u64::try_from(n).ok())
        .ok_or_else(|| format!("{entry} has First {first} and Last {last}, not a range of records"))
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;
    use std::io::Write;
    use std::path::Path;

    use super::{MAX_INDEX_DEPTH, check};
    use crate::cdf_pose::read_variable;

    const CDF_CHAR: i32 = 51;
    const CDF_DOUBLE: i32 = 45;

    /// A CDF file written field by field. Named fields keep their position and width, records their
    /// start, so that a test can link or overwrite them.
    struct Tiny {
        b: Vec<u8>,
        /// CDF 3 (8-byte sizes and offsets) or 2.6 (4-byte).
        wide: bool,
        at: HashMap<String, (usize, usize)>,
    }

    impl Tiny {
        fn field(&mut self, name: &str, bytes: &[u8]) {
            if !name.is_empty() {
                self.at.insert(name.into(), (self.b.len(), bytes.len()));
            }
            self.b.extend_from_slice(bytes);
        }

        fn i4(&mut self, name: &str, v: i32) {
            self.field(name, &v.to_be_bytes());
        }

        fn off(&mut self, name: &str, v: i64) {
            match self.wide {
                true => self.field(name, &v.to_be_bytes()),
                false => self.field(name, &i32::try_from(v).unwrap().to_be_bytes()),
            }
        }

        fn set(&mut self, name: &str, v: i64) {
            let (at, width) = self.at[name];
            let bytes = match width {
                8 => v.to_be_bytes().to_vec(),
                _ => i32::try_from(v).unwrap().to_be_bytes().to_vec(),
            };
            self.b[at..at + width].copy_from_slice(&bytes);
        }

        fn start(&self, record: &str) -> i64 {
            self.at[record].0 as i64
        }

        fn link(&mut self, field: &str, record: &str) {
            self.set(field, self.start(record));
        }

        /// Starts record `name` of RecordType `code`; [`Tiny::end`] sets its RecordSize.
        fn begin(&mut self, name: &str, code: i32) {
            self.at.insert(name.into(), (self.b.len(), 0));
            self.off(&format!("{name}.RecordSize"), 0);
            self.i4("", code);
        }

        fn end(&mut self, name: &str) {
            let size = self.b.len() as i64 - self.start(name);
            self.set(&format!("{name}.RecordSize"), size);
        }

        fn name(&mut self, name: &str, len: usize) {
            let mut b = name.as_bytes().to_vec();
            b.resize(len, 0);
            self.field("", &b);
        }

        /// A variable of doubles, two records varying in every dimension (`z_dims` for a zVariable, the
        /// GDR's one of 3 for an rVariable), with a pad value.
        fn vdr(&mut self, rec: &str, code: i32, var: &str, z_dims: Option<&[i32]>) {
            let f = |name: &str| format!("{rec}.{name}");
            self.begin(rec, code);
            self.off(&f("VDRnext"), 0);
            self.i4(&f("DataType"), CDF_DOUBLE);
            self.i4("", 1); // MaxRec
            self.off(&f("VXRhead"), 0);
            self.off("", 0); // VXRtail
            for v in [3, 0, 0, -1, -1] {
                self.i4("", v); // Flags (record variance, pad value), SRecords, rfuB, rfuC, rfuF
            }
            self.i4(&f("NumElems"), 1);
            self.i4("", 0); // Num
            self.off("", -1); // CPRorSPRoffset
            self.i4("", 0); // BlockingFactor
            self.name(var, 256);
            let dims = z_dims.map_or(1, |d| d.len());
            if let Some(d) = z_dims {
                self.i4(&f("zNumDims"), d.len() as i32);
                for (i, &s) in d.iter().enumerate() {
                    self.i4(&f(&format!("zDimSizes{i}")), s);
                }
            }
            for _ in 0..dims {
                self.i4("", -1); // DimVarys
            }
            self.field(&f("pad"), &0f64.to_le_bytes());
            self.end(rec);
        }

        /// A VXR of entries (First, Last), their Offsets set by [`Tiny::link`].
        fn vxr(&mut self, rec: &str, ranges: &[(i32, i32)]) {
            self.begin(rec, 6);
            self.off(&format!("{rec}.VXRnext"), 0);
            self.i4(&format!("{rec}.NumEntries"), ranges.len() as i32);
            self.i4("", ranges.len() as i32); // NusedEntries
            for (i, r) in ranges.iter().enumerate() {
                self.i4(&format!("{rec}.First{i}"), r.0);
            }
            for (i, r) in ranges.iter().enumerate() {
                self.i4(&format!("{rec}.Last{i}"), r.1);
            }
            for i in 0..ranges.len() {
                self.off(&format!("{rec}.Offset{i}"), -1);
            }
            self.end(rec);
        }

        fn vvr(&mut self, rec: &str, values: &[u8]) {
            self.begin(rec, 7);
            self.field("", values);
            self.end(rec);
        }

        fn cvvr(&mut self, rec: &str, values: &[u8]) {
            let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
            gz.write_all(values).unwrap();
            let data = gz.finish().unwrap();
            self.begin(rec, 13);
            self.i4("", 0); // rfuA
            self.off(&format!("{rec}.CSize"), data.len() as i64);
            self.field("", &data);
            self.end(rec);
        }

        fn adr(&mut self) {
            self.begin("ADR", 4);
            self.off("ADR.ADRnext", 0);
            self.off("ADR.AgrEDRhead", 0);
            for v in [1, 0, 1, 0, 0] {
                self.i4("", v); // Scope (global), Num, NgrEntries, MAXgrEntry, rfuA
            }
            self.off("ADR.AzEDRhead", 0);
            for v in [1, 0, -1] {
                self.i4("", v); // NzEntries, MAXzEntry, rfuE
            }
            self.name("units", if self.wide { 256 } else { 64 });
            self.end("ADR");
        }

        fn aedr(&mut self, rec: &str, code: i32, data_type: i32, num_elems: i32, value: &[u8]) {
            self.begin(rec, code);
            self.off(&format!("{rec}.AEDRnext"), 0);
            for v in [0, data_type, 0] {
                self.i4("", v); // AttrNum, DataType, Num
            }
            self.i4(&format!("{rec}.NumElems"), num_elems);
            for v in [1, 0, 0, -1, -1] {
                self.i4("", v); // NumStrings, rfuB, rfuC, rfuD, rfuE
            }
            self.field(&format!("{rec}.value"), value);
            self.end(rec);
        }

        fn uir(&mut self) {
            self.begin("UIR", -1);
            self.off("UIR.NextUIR", 0);
            self.off("UIR.PrevUIR", 0);
            self.field("", &[0; 8]);
            self.end("UIR");
        }
    }

    fn doubles(values: impl IntoIterator<Item = i32>) -> Vec<u8> {
        values
            .into_iter()
            .flat_map(|v| f64::from(v).to_le_bytes())
            .collect()
    }

    /// A small CDF file (3.9 when `wide`, 2.6 otherwise, little-endian values) with each kind of record the
    /// decoder reads: zVariable `Pose`, two records of [2, 3] doubles 0 to 11, the first in a VVR, the
    /// second GZIP-compressed in a CVVR under a nested VXR; rVariable `R`, two records of [3] doubles 100 to
    /// 105; an attribute with a global and a zVariable entry; an unused record.
    fn tiny(wide: bool) -> Tiny {
        let mut t = Tiny {
            b: Vec::new(),
            wide,
            at: HashMap::new(),
        };
        let magic: u32 = if wide { 0xcdf3_0001 } else { 0xcdf2_6002 };
        t.field("", &magic.to_be_bytes());
        t.field("", &0x0000_ffffu32.to_be_bytes());
        t.begin("CDR", 1);
        t.off("CDR.GDRoffset", 0);
        let (version, release) = if wide { (3, 9) } else { (2, 6) };
        // Version, Release, Encoding (IBM PC), Flags (row-major, single file), rfuA, rfuB, Increment,
        // Identifier, rfuE; Copyright.
        for v in [version, release, 6, 3, 0, 0, 0, -1, -1] {
            t.i4("", v);
        }
        t.field("", &[0; 256]);
        t.end("CDR");
        t.begin("GDR", 2);
        for name in ["rVDRhead", "zVDRhead", "ADRhead", "eof"] {
            t.off(&format!("GDR.{name}"), 0);
        }
        for v in [1, 1, 1] {
            t.i4("", v); // rNumVars, NumAttr, rMaxRec
        }
        t.i4("GDR.rNumDims", 1);
        t.i4("", 1); // zNumVars
        t.off("GDR.UIRhead", 0);
        for v in [0, -1, -1, 3] {
            t.i4("", v); // rfuC, LeapSecondLastUpdated, rfuE, rDimSizes
        }
        t.end("GDR");
        t.vdr("zVDR", 8, "Pose", Some(&[2, 3]));
        t.vdr("rVDR", 3, "R", None);
        t.vxr("VXR1", &[(0, 0), (1, 1)]);
        t.vxr("VXR2", &[(1, 1)]);
        t.vxr("VXR3", &[(0, 1)]);
        t.vvr("VVR1", &doubles(0..6));
        t.cvvr("CVVR", &doubles(6..12));
        t.vvr("VVR2", &doubles(100..106));
        t.adr();
        t.aedr("AgrEDR", 5, CDF_CHAR, 2, b"mm");
        t.aedr("AzEDR", 9, CDF_DOUBLE, 1, &1f64.to_le_bytes());
        t.uir();
        for (field, record) in [
            ("CDR.GDRoffset", "GDR"),
            ("GDR.rVDRhead", "rVDR"),
            ("GDR.zVDRhead", "zVDR"),
            ("GDR.ADRhead", "ADR"),
            ("GDR.UIRhead", "UIR"),
            ("zVDR.VXRhead", "VXR1"),
            ("rVDR.VXRhead", "VXR3"),
            ("VXR1.Offset0", "VVR1"),
            ("VXR1.Offset1", "VXR2"),
            ("VXR2.Offset0", "CVVR"),
            ("VXR3.Offset0", "VVR2"),
            ("ADR.AgrEDRhead", "AgrEDR"),
            ("ADR.AzEDRhead", "AzEDR"),
        ] {
            t.link(field, record);
        }
        t.set("GDR.eof", t.b.len() as i64);
        t
    }

    /// [`read_variable`] of `name` from `bytes` in a file Walking.cdf; an error as its message.
    fn read(bytes: &[u8], name: &str) -> Result<(Vec<f64>, Vec<usize>), String> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("Walking.cdf");
        std::fs::write(&path, bytes).unwrap();
        read_variable(&path, name).map_err(|e| e.to_string())
    }

    /// Asserts that `Pose` is refused from `t` with a message naming the file, `record` (a name of
    /// [`tiny`]'s, its kind before any digits) at its byte and `words`.
    fn assert_refused(t: &Tiny, record: &str, words: &str, case: &str) {
        let e = read(&t.b, "Pose").unwrap_err();
        let kind = record.trim_end_matches(|c: char| c.is_ascii_digit());
        let at = format!("{kind} at byte {}", t.start(record));
        assert!(
            e.contains("Walking.cdf") && e.contains(&at) && e.contains(words),
            "{case}: expected `{at}` and `{words}` in: {e}"
        );
    }

    /// The files the guard passes still read, with every kind of record it checks; so do cdflib's
    /// (tests/fixtures/h36m); and a file compressed as a whole is still named so.
    #[test]
    fn cdf_files_within_their_bounds_read() {
        for wide in [true, false] {
            let t = tiny(wide);
            assert_eq!(check(&t.b), Ok(()), "wide {wide}");
            let pose = ((0..12).map(f64::from).collect(), vec![2, 3]);
            assert_eq!(read(&t.b, "Pose"), Ok(pose), "wide {wide}");
            let r = ((100..106).map(f64::from).collect(), vec![3]);
            assert_eq!(read(&t.b, "R"), Ok(r), "wide {wide}");
        }
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/h36m");
        for name in [
            "pose_float_one_record.cdf",
            "pose_double_gzip.cdf",
            "pose_double_column_major.cdf",
            "pose_double_rvariable.cdf",
        ] {
            assert_eq!(
                check(&std::fs::read(dir.join(name)).unwrap()),
                Ok(()),
                "{name}"
            );
        }
        let mut t = tiny(true);
        t.b[4..8].copy_from_slice(&0xcccc_0001u32.to_be_bytes());
        let e = read(&t.b, "Pose").unwrap_err();
        assert!(e.contains("compressed") && e.contains("cdfconvert"), "{e}");
    }

    /// Each count or size the decoder allocates from, set past what the file holds: refused, named with
    /// its record and value. Without the guard (tried once, with it switched off, under `ulimit -v 3000000`)
    /// the decoder first asks for (CdfType values and VVR record slots are 32 bytes each) 8 GiB for
    /// rNumDims, zNumDims or the AgrEDR's 2^31 chars, 16 GiB for NumEntries, 24 GiB for a record of
    /// 3 x 2^28 values, 64 GiB for a pad value, the AzEDR's value or Last 2^31 - 2, 1 TiB or 8 EiB for
    /// CSize or the UIR's RecordSize: "memory allocation of N bytes failed", and the process aborts, so
    /// these cases cannot run without the guard. The others end in errors that name no field (negative
    /// counts, First after Last, a 2 GiB CSize in CDF 2.6, an overflow panic of the UIR's RecordSize - 28
    /// or of the values per record) or, for the RecordSizes the decoder ignores (VVR, GDR, VXR, CDR), in
    /// a read.
    #[test]
    fn cdf_sizes_past_the_file_are_refused() {
        let (tib, max4) = (1i64 << 40, i64::from(i32::MAX));
        let cases: &[(&str, i64, &str, &str)] = &[
            ("GDR.rNumDims", max4, "GDR", "rNumDims 2147483647"),
            ("GDR.rNumDims", -1, "GDR", "rNumDims -1 is a negative count"),
            ("zVDR.zNumDims", max4, "zVDR", "zNumDims 2147483647"),
            (
                "zVDR.NumElems",
                max4,
                "zVDR",
                "NumElems (of the pad value) 2147483647",
            ),
            (
                "rVDR.NumElems",
                -5,
                "rVDR",
                "NumElems (of the pad value) -5",
            ),
            (
                "zVDR.zDimSizes0",
                max4,
                "zVDR",
                "overflows the decoder's 32-bit count",
            ),
            ("zVDR.zDimSizes0", 1 << 28, "VVR1", "805306368 values"),
            ("VXR1.NumEntries", max4, "VXR1", "NumEntries 2147483647"),
            ("VXR1.Last0", max4 - 1, "VVR1", "Last 2147483646"),
            ("VXR1.First0", 5, "VXR1", "First 5 and Last 0, not a range"),
            ("CVVR.CSize", tib, "CVVR", "CSize 1099511627776"),
            ("CVVR.CSize", i64::MAX, "CVVR", "CSize 9223372036854775807"),
            ("CVVR.CSize", -1, "CVVR", "CSize -1"),
            ("UIR.RecordSize", tib, "UIR", "RecordSize 1099511627776"),
            ("UIR.RecordSize", 20, "UIR", "RecordSize 20, too small"),
            ("AgrEDR.NumElems", max4, "AgrEDR", "NumElems 2147483647"),
            ("AzEDR.NumElems", max4, "AzEDR", "NumElems 2147483647"),
            (
                "VVR1.RecordSize",
                i64::MAX,
                "VVR1",
                "RecordSize 9223372036854775807",
            ),
            ("GDR.RecordSize", -1, "GDR", "RecordSize -1"),
            ("VXR1.RecordSize", 20, "VXR1", "RecordSize 20"),
            ("CDR.RecordSize", tib, "CDR", "RecordSize 1099511627776"),
        ];
        for &(field, value, record, words) in cases {
            let mut t = tiny(true);
            t.set(field, value);
            assert_refused(&t, record, words, &format!("{field} = {value}"));
        }
        // CDF 2.6: 4-byte sizes and offsets.
        let cases: &[(&str, i64, &str, &str)] = &[
            ("CVVR.CSize", max4, "CVVR", "CSize 2147483647"),
            ("VXR1.NumEntries", max4, "VXR1", "NumEntries 2147483647"),
            ("VXR1.Last0", max4 - 1, "VVR1", "Last 2147483646"),
            (
                "zVDR.NumElems",
                -1,
                "zVDR",
                "NumElems (of the pad value) -1",
            ),
            ("UIR.RecordSize", 12, "UIR", "RecordSize 12, too small"),
        ];
        for &(field, value, record, words) in cases {
            let mut t = tiny(false);
            t.set(field, value);
            assert_refused(&t, record, words, &format!("CDF 2.6: {field} = {value}"));
        }
    }

    /// The rVDR's DimVarys are counted by the GDR's rNumDims: a GDR grown to hold 200 rDimSizes leaves
    /// the rVDR too small for 200 DimVarys. (Without the guard the decoder reads them on through the
    /// records after the rVDR, and the file reads.)
    #[test]
    fn cdf_rvariable_dimensions_must_fit_the_rvdr() {
        let mut t = tiny(true);
        t.set("GDR.RecordSize", 84 + 4 * 200);
        t.set("GDR.rNumDims", 200);
        assert_refused(&t, "rVDR", "the GDR's rNumDims 200", "rNumDims");
    }

    /// Links back. The decoder follows chains until a link of 0 and index entries down to their leaves,
    /// remembering nothing: a chain linked back to itself never ends (its records pile up until memory
    /// runs out), an index entry pointing up recurses until the stack overflows (an abort), and a record
    /// linked twice is decoded twice (VXR1's second entry to VVR1: without the guard the file reads, with
    /// record 0 twice).
    #[test]
    fn cdf_links_back_are_refused() {
        for (field, record) in [
            ("zVDR.VDRnext", "zVDR"),
            ("VXR2.Offset0", "VXR1"),
            ("VXR1.Offset1", "VVR1"),
            ("ADR.ADRnext", "ADR"),
            ("AgrEDR.AEDRnext", "AgrEDR"),
            ("UIR.NextUIR", "UIR"),
        ] {
            let mut t = tiny(true);
            t.link(field, record);
            let e = read(&t.b, "Pose").unwrap_err();
            let back = format!("points back to byte {}", t.start(record));
            assert!(e.contains(&back), "{field}: {e}");
        }
    }

    /// An index tree [`MAX_INDEX_DEPTH`] levels deep reads; a level more is refused. (The decoder recurses
    /// a level at a time; it would read this one, but a file could nest until the stack overflows.)
    #[test]
    fn cdf_index_trees_past_the_depth_cap_are_refused() {
        for (levels, reads) in [(MAX_INDEX_DEPTH, true), (MAX_INDEX_DEPTH + 1, false)] {
            let mut t = tiny(true);
            // VXR1 and VXR2 are levels 1 and 2; more between VXR2 and the CVVR.
            let mut parent = "VXR2".to_string();
            for k in 3..=levels {
                let rec = format!("deep{k}");
                t.vxr(&rec, &[(1, 1)]);
                t.link(&format!("{parent}.Offset0"), &rec);
                parent = rec;
            }
            t.link(&format!("{parent}.Offset0"), "CVVR");
            match read(&t.b, "Pose") {
                Ok((values, _)) => assert!(reads && values.len() == 12, "{levels} levels"),
                Err(e) => assert!(
                    !reads && e.contains("more than 32 levels"),
                    "{levels} levels: {e}"
                ),
            }
        }
    }

    /// Records that each hold what they declare but overlap: two attribute entries stretched to the end of
    /// the file, their values filling them, would have the decoder read more than the file holds. (It
    /// reads this file; a file of many such records would multiply its size.)
    #[test]
    fn cdf_records_overlapping_past_the_file_are_refused() {
        let mut t = tiny(true);
        t.b.extend([0; 4096]);
        let len = t.b.len() as i64;
        for (rec, width) in [("AgrEDR", 1), ("AzEDR", 8)] {
            t.set(&format!("{rec}.RecordSize"), len - t.start(rec));
            let value = t.at[&format!("{rec}.value")].0 as i64;
            t.set(&format!("{rec}.NumElems"), (len - value) / width);
        }
        let e = read(&t.b, "Pose").unwrap_err();
        assert!(
            e.contains(&format!("more than the file's {len} bytes: they overlap")),
            "{e}"
        );
    }
}
