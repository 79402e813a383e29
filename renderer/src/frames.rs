//! Frame ranges (`--frames 1-240[:step]`, `--frame N`, REST `frames`) and output-name patterns
//! (`shot.####.exr`: the run of `#` is the zero-padded frame number).

use serde::{Deserialize, Serialize};

/// Most frames one job or command renders.
pub const MAX_FRAMES: u32 = 100_000;
/// Largest frame number.
pub const MAX_FRAME: u32 = 10_000_000;

/// First..=last every `step` frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameRange {
    pub first: u32,
    pub last: u32,
    pub step: u32,
}

impl FrameRange {
    pub fn single(n: u32) -> Self {
        FrameRange { first: n, last: n, step: 1 }
    }

    /// Parses `N`, `A-B` or `A-B:S` (A ≤ B, S ≥ 1), bounded by MAX_FRAME and MAX_FRAMES.
    pub fn parse(s: &str) -> Result<Self, String> {
        let s = s.trim();
        let num = |x: &str, what: &str| -> Result<u32, String> {
            let v: u64 = x.trim().parse().map_err(|_| format!("{what} '{x}' is not a frame number"))?;
            if v > MAX_FRAME as u64 {
                return Err(format!("{what} {v} is over {MAX_FRAME}"));
            }
            Ok(v as u32)
        };
        let (range, step) = match s.split_once(':') {
            Some((r, st)) => (r, num(st, "step")?),
            None => (s, 1),
        };
        if step == 0 {
            return Err("step must be at least 1".into());
        }
        let (first, last) = match range.split_once('-') {
            Some((a, b)) => (num(a, "first frame")?, num(b, "last frame")?),
            None => {
                let n = num(range, "frame")?;
                (n, n)
            }
        };
        if first > last {
            return Err(format!("first frame {first} is after the last {last}"));
        }
        let r = FrameRange { first, last, step };
        if r.count() > MAX_FRAMES {
            return Err(format!("{} frames, more than {MAX_FRAMES}", r.count()));
        }
        Ok(r)
    }

    pub fn count(&self) -> u32 {
        (self.last - self.first) / self.step + 1
    }

    pub fn iter(&self) -> impl Iterator<Item = u32> {
        (self.first..=self.last).step_by(self.step as usize)
    }
}

impl std::fmt::Display for FrameRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.first == self.last {
            write!(f, "{}", self.first)
        } else if self.step == 1 {
            write!(f, "{}-{}", self.first, self.last)
        } else {
            write!(f, "{}-{}:{}", self.first, self.last, self.step)
        }
    }
}

impl std::str::FromStr for FrameRange {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        FrameRange::parse(s)
    }
}

/// `pattern` with its last run of `#` replaced by `frame`, zero-padded to the run's length
/// (`shot.####.exr`, 7 → `shot.0007.exr`). Without `#`, `.NNNN` is put before the extension so
/// frames never overwrite each other.
pub fn frame_path(pattern: &str, frame: u32) -> String {
    if let Some(end) = pattern.rfind('#') {
        let start = pattern[..=end].trim_end_matches('#').len();
        let width = end + 1 - start;
        return format!("{}{:0width$}{}", &pattern[..start], frame, &pattern[end + 1..], width = width);
    }
    match pattern.rfind('.') {
        Some(dot) if !pattern[dot..].contains('/') => format!("{}.{:04}{}", &pattern[..dot], frame, &pattern[dot..]),
        _ => format!("{pattern}.{frame:04}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_parse_and_count() {
        assert_eq!(FrameRange::parse("1-240").map(|r| r.count()), Ok(240));
        assert_eq!(FrameRange::parse("1-240:10").map(|r| r.iter().collect::<Vec<_>>().len()), Ok(24));
        assert_eq!(FrameRange::parse("7"), Ok(FrameRange::single(7)));
        assert_eq!(FrameRange::parse("0-3").map(|r| r.iter().collect::<Vec<_>>()), Ok(vec![0, 1, 2, 3]));
        for bad in ["", "5-1", "1-10:0", "a-b", "1-99999999", "0-200000"] {
            assert!(FrameRange::parse(bad).is_err(), "{bad}");
        }
        assert_eq!(FrameRange::parse("1-9:2").map(|r| r.to_string()), Ok("1-9:2".to_string()));
    }

    #[test]
    fn patterns_pad_the_frame() {
        assert_eq!(frame_path("shot.####.exr", 7), "shot.0007.exr");
        assert_eq!(frame_path("out/f#.exr", 12), "out/f12.exr");
        assert_eq!(frame_path("render.exr", 3), "render.0003.exr");
        assert_eq!(frame_path("dir.v2/render", 3), "dir.v2/render.0003");
    }
}
