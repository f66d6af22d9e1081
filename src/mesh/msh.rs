//! Reader for Gmsh's MSH 4.1 format, ASCII and binary.
//!
//! Written by hand because no maintained crate reads MSH 4.1 with its `$PhysicalNames`, and because a
//! malformed patient mesh must be refused with the line (ASCII) or byte offset (binary) where it goes
//! wrong, never with a panic. Only what nak needs is kept: nodes, elements, entities' physical tags and
//! physical names; other sections are skipped.

use std::collections::HashMap;

use super::MeshError;

/// The parts of an MSH file that describe a labelled mesh.
#[derive(Debug, Default)]
pub struct MshFile {
    /// Node tags in file order.
    pub node_tags: Vec<u64>,
    /// Node coordinates in file order.
    pub node_coords: Vec<[f64; 3]>,
    pub element_blocks: Vec<ElementBlock>,
    /// `(dimension, physical tag) -> name`.
    pub physical_names: HashMap<(i32, i32), String>,
    /// `(dimension, entity tag) -> physical tags`.
    pub entity_physicals: HashMap<(i32, i32), Vec<i32>>,
}

/// One `$Elements` block: elements of one type on one geometric entity.
#[derive(Debug)]
pub struct ElementBlock {
    pub entity_dim: i32,
    pub entity_tag: i32,
    pub element_type: i32,
    pub element_tags: Vec<u64>,
    /// Node tags, `nodes_per_element` per element.
    pub connectivity: Vec<u64>,
    pub nodes_per_element: usize,
}

/// Gmsh element type codes that nak interprets.
pub const TRIANGLE: i32 = 2;
pub const TETRAHEDRON: i32 = 4;
pub const POINT: i32 = 15;

/// Nodes per element for Gmsh's element types (MSH 4.1 reference, "elm-type").
fn nodes_per_element(element_type: i32) -> Option<usize> {
    Some(match element_type {
        1 => 2,
        2 => 3,
        3 => 4,
        4 => 4,
        5 => 8,
        6 => 6,
        7 => 5,
        8 => 3,
        9 => 6,
        10 => 9,
        11 => 10,
        12 => 27,
        13 => 18,
        14 => 14,
        15 => 1,
        16 => 8,
        17 => 20,
        18 => 15,
        19 => 13,
        20 => 9,
        21 => 10,
        26 => 4,
        29 => 20,
        30 => 35,
        31 => 56,
        _ => return None,
    })
}

/// Parses MSH 4.1 bytes; `origin` names the file in error messages.
pub fn parse(bytes: &[u8], origin: &str) -> Result<MshFile, MeshError> {
    let mut cur = Cursor {
        data: bytes,
        pos: 0,
        binary: false,
        big_endian: false,
        origin,
    };
    let mut file = MshFile::default();
    let mut saw_format = false;
    while let Some(header) = cur.next_section()? {
        match header.as_str() {
            "$MeshFormat" => {
                cur.mesh_format()?;
                saw_format = true;
            }
            _ if !saw_format => {
                return Err(cur.error("the file does not start with $MeshFormat: not an MSH file"));
            }
            "$PhysicalNames" => cur.physical_names(&mut file)?,
            "$Entities" => cur.entities(&mut file)?,
            "$Nodes" => cur.nodes(&mut file)?,
            "$Elements" => cur.elements(&mut file)?,
            other => {
                cur.skip_section(&other[1..])?;
                continue;
            }
        }
        cur.section_end(&header[1..])?;
    }
    if !saw_format {
        return Err(cur.error("empty file: no $MeshFormat section"));
    }
    Ok(file)
}

struct Cursor<'a> {
    data: &'a [u8],
    pos: usize,
    binary: bool,
    big_endian: bool,
    origin: &'a str,
}

impl Cursor<'_> {
    fn error(&self, message: impl Into<String>) -> MeshError {
        let location = if self.binary {
            format!("byte {}", self.pos)
        } else {
            let upto = &self.data[..self.pos.min(self.data.len())];
            format!("line {}", upto.iter().filter(|&&b| b == b'\n').count() + 1)
        };
        MeshError::Parse {
            path: self.origin.to_owned(),
            location,
            message: message.into(),
        }
    }

    fn skip_whitespace(&mut self) {
        while self.pos < self.data.len() && self.data[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
    }

    /// The next `$Section` header line, or `None` at the end of the file.
    fn next_section(&mut self) -> Result<Option<String>, MeshError> {
        self.skip_whitespace();
        if self.pos >= self.data.len() {
            return Ok(None);
        }
        let start = self.pos;
        let line = self.line()?;
        if !line.starts_with('$') {
            self.pos = start;
            return Err(self.error(format!(
                "expected a section header such as $Nodes, found {:?}",
                truncate(&line)
            )));
        }
        Ok(Some(line))
    }

    /// The rest of the current line, without its line ending.
    fn line(&mut self) -> Result<String, MeshError> {
        let start = self.pos;
        let end = self.data[start..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(self.data.len(), |p| start + p);
        self.pos = (end + 1).min(self.data.len());
        let text = std::str::from_utf8(&self.data[start..end])
            .map_err(|_| self.error("expected a text line, found bytes that are not UTF-8"))?;
        Ok(text.trim_end_matches('\r').to_owned())
    }

    fn section_end(&mut self, name: &str) -> Result<(), MeshError> {
        self.skip_whitespace();
        let expected = format!("$End{name}");
        let line = self.line()?;
        if line.trim() != expected {
            return Err(self.error(format!(
                "expected {expected}, found {:?} (counts in the section header disagree with its content?)",
                truncate(&line)
            )));
        }
        Ok(())
    }

    fn skip_section(&mut self, name: &str) -> Result<(), MeshError> {
        let end = format!("$End{name}");
        let found = self
            .data
            .get(self.pos..)
            .and_then(|rest| rest.windows(end.len()).position(|w| w == end.as_bytes()));
        match found {
            Some(offset) => {
                self.pos += offset;
                self.line()?;
                Ok(())
            }
            None => Err(self.error(format!("section ${name} has no {end}"))),
        }
    }

    fn mesh_format(&mut self) -> Result<(), MeshError> {
        self.skip_whitespace();
        let line = self.line()?;
        let fields: Vec<&str> = line.split_whitespace().collect();
        let [version, file_type, data_size] = fields[..] else {
            return Err(self.error(format!("malformed $MeshFormat line {line:?}")));
        };
        if version != "4.1" {
            return Err(self.error(format!(
                "MSH version {version} is not supported: nak reads MSH 4.1 \
                 (re-export with gmsh -format msh41, or Mesh.MshFileVersion = 4.1)"
            )));
        }
        if data_size != "8" {
            return Err(self.error(format!("data size {data_size} is not supported (expected 8)")));
        }
        match file_type {
            "0" => Ok(()),
            "1" => {
                self.binary = true;
                let raw = self.take::<4>()?;
                self.big_endian = match (u32::from_le_bytes(raw), u32::from_be_bytes(raw)) {
                    (1, _) => false,
                    (_, 1) => true,
                    _ => return Err(self.error("binary MSH endianness marker is not 1")),
                };
                Ok(())
            }
            other => Err(self.error(format!("unknown MSH file type {other}"))),
        }
    }

    fn take<const N: usize>(&mut self) -> Result<[u8; N], MeshError> {
        let slice = self
            .data
            .get(self.pos..self.pos + N)
            .ok_or_else(|| self.error("unexpected end of file"))?;
        self.pos += N;
        let mut out = [0u8; N];
        out.copy_from_slice(slice);
        Ok(out)
    }

    fn token(&mut self, what: &str) -> Result<&str, MeshError> {
        self.skip_whitespace();
        let start = self.pos;
        while self.pos < self.data.len() && !self.data[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
        if start == self.pos {
            return Err(self.error(format!("unexpected end of file: expected {what}")));
        }
        std::str::from_utf8(&self.data[start..self.pos])
            .map_err(|_| self.error(format!("expected {what}, found bytes that are not UTF-8")))
    }

    fn parse_token<T: std::str::FromStr>(&mut self, what: &str) -> Result<T, MeshError> {
        let start = self.pos;
        let token = self.token(what)?.to_owned();
        token.parse().map_err(|_| {
            self.pos = start;
            self.skip_whitespace();
            self.error(format!("expected {what}, found {:?}", truncate(&token)))
        })
    }

    fn size(&mut self, what: &str) -> Result<u64, MeshError> {
        if !self.binary {
            return self.parse_token(what);
        }
        let raw = self.take::<8>()?;
        Ok(if self.big_endian {
            u64::from_be_bytes(raw)
        } else {
            u64::from_le_bytes(raw)
        })
    }

    /// A count that sizes an allocation: bounded by what the remaining bytes could possibly hold.
    fn count(&mut self, what: &str) -> Result<usize, MeshError> {
        let n = self.size(what)?;
        let remaining = (self.data.len() - self.pos) as u64;
        if n > remaining {
            return Err(self.error(format!("{what} = {n} exceeds what the rest of the file can hold")));
        }
        Ok(n as usize)
    }

    fn int(&mut self, what: &str) -> Result<i32, MeshError> {
        if !self.binary {
            return self.parse_token(what);
        }
        let raw = self.take::<4>()?;
        Ok(if self.big_endian {
            i32::from_be_bytes(raw)
        } else {
            i32::from_le_bytes(raw)
        })
    }

    fn float(&mut self, what: &str) -> Result<f64, MeshError> {
        let value = if self.binary {
            let raw = self.take::<8>()?;
            if self.big_endian {
                f64::from_be_bytes(raw)
            } else {
                f64::from_le_bytes(raw)
            }
        } else {
            self.parse_token(what)?
        };
        if !value.is_finite() {
            return Err(self.error(format!("{what} is not a finite number ({value})")));
        }
        Ok(value)
    }

    fn physical_names(&mut self, file: &mut MshFile) -> Result<(), MeshError> {
        // Always ASCII, even in binary files.
        let binary = std::mem::replace(&mut self.binary, false);
        let count = self.count("the number of physical names")?;
        for _ in 0..count {
            let dim: i32 = self.parse_token("a physical group dimension")?;
            let tag: i32 = self.parse_token("a physical group tag")?;
            self.skip_whitespace();
            let rest = self.line()?;
            let name = rest.trim().trim_matches('"').to_owned();
            if name.is_empty() {
                return Err(self.error(format!("physical group ({dim}, {tag}) has an empty name")));
            }
            file.physical_names.insert((dim, tag), name);
        }
        self.binary = binary;
        Ok(())
    }

    fn entities(&mut self, file: &mut MshFile) -> Result<(), MeshError> {
        let mut counts = [0usize; 4];
        for (dim, count) in counts.iter_mut().enumerate() {
            *count = self.count(&format!("the number of dimension-{dim} entities"))?;
        }
        for (dim, &count) in counts.iter().enumerate() {
            for _ in 0..count {
                let tag = self.int("an entity tag")?;
                let coordinates = if dim == 0 { 3 } else { 6 };
                for _ in 0..coordinates {
                    self.float("an entity coordinate")?;
                }
                let n_physical = self.count("the number of physical tags")?;
                let mut physicals = Vec::with_capacity(n_physical);
                for _ in 0..n_physical {
                    physicals.push(self.int("a physical tag")?);
                }
                if dim > 0 {
                    let n_bounding = self.count("the number of bounding entities")?;
                    for _ in 0..n_bounding {
                        self.int("a bounding entity tag")?;
                    }
                }
                file.entity_physicals.insert((dim as i32, tag), physicals);
            }
        }
        Ok(())
    }

    fn nodes(&mut self, file: &mut MshFile) -> Result<(), MeshError> {
        let blocks = self.count("the number of node blocks")?;
        let total = self.count("the number of nodes")?;
        self.size("the minimum node tag")?;
        self.size("the maximum node tag")?;
        file.node_tags.reserve(total);
        file.node_coords.reserve(total);
        for _ in 0..blocks {
            let entity_dim = self.int("a node block's entity dimension")?;
            self.int("a node block's entity tag")?;
            let parametric = self.int("a node block's parametric flag")? != 0;
            let count = self.count("the number of nodes in a block")?;
            for _ in 0..count {
                file.node_tags.push(self.size("a node tag")?);
            }
            let extra = if parametric { entity_dim.clamp(0, 3) as usize } else { 0 };
            for _ in 0..count {
                let x = self.float("a node x coordinate")?;
                let y = self.float("a node y coordinate")?;
                let z = self.float("a node z coordinate")?;
                for _ in 0..extra {
                    self.float("a parametric node coordinate")?;
                }
                file.node_coords.push([x, y, z]);
            }
        }
        if file.node_tags.len() != total {
            return Err(self.error(format!(
                "$Nodes header announces {total} nodes but its blocks hold {}",
                file.node_tags.len()
            )));
        }
        Ok(())
    }

    fn elements(&mut self, file: &mut MshFile) -> Result<(), MeshError> {
        let blocks = self.count("the number of element blocks")?;
        self.size("the number of elements")?;
        self.size("the minimum element tag")?;
        self.size("the maximum element tag")?;
        for _ in 0..blocks {
            let entity_dim = self.int("an element block's entity dimension")?;
            let entity_tag = self.int("an element block's entity tag")?;
            let element_type = self.int("an element type")?;
            let per = nodes_per_element(element_type)
                .ok_or_else(|| self.error(format!("unknown element type {element_type}")))?;
            let count = self.count("the number of elements in a block")?;
            let mut block = ElementBlock {
                entity_dim,
                entity_tag,
                element_type,
                element_tags: Vec::with_capacity(count),
                connectivity: Vec::with_capacity(count * per),
                nodes_per_element: per,
            };
            for _ in 0..count {
                block.element_tags.push(self.size("an element tag")?);
                for _ in 0..per {
                    block.connectivity.push(self.size("an element's node tag")?);
                }
            }
            file.element_blocks.push(block);
        }
        Ok(())
    }
}

fn truncate(text: &str) -> String {
    text.chars().take(60).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const ONE_TET: &str = "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n\
        $PhysicalNames\n1\n3 7 \"liver\"\n$EndPhysicalNames\n\
        $Entities\n0 0 0 1\n1 0 0 0 1 1 1 1 7 0\n$EndEntities\n\
        $Nodes\n1 4 1 4\n3 1 0 4\n1\n2\n3\n4\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n$EndNodes\n\
        $Elements\n1 1 1 1\n3 1 4 1\n1 1 2 3 4\n$EndElements\n";

    #[test]
    fn reads_a_single_ascii_tetrahedron() {
        let file = parse(ONE_TET.as_bytes(), "one.msh").unwrap();
        assert_eq!(file.node_tags, vec![1, 2, 3, 4]);
        assert_eq!(file.node_coords[3], [0.0, 0.0, 1.0]);
        assert_eq!(file.element_blocks[0].connectivity, vec![1, 2, 3, 4]);
        assert_eq!(file.physical_names[&(3, 7)], "liver");
        assert_eq!(file.entity_physicals[&(3, 1)], vec![7]);
    }

    #[test]
    fn reports_the_line_of_a_bad_number() {
        let bad = ONE_TET.replace("0 1 0\n", "0 one 0\n");
        let err = parse(bad.as_bytes(), "bad.msh").unwrap_err().to_string();
        assert!(err.contains("bad.msh: line 21"), "{err}");
        assert!(err.contains("\"one\""), "{err}");
    }

    #[test]
    fn refuses_msh2() {
        let old = ONE_TET.replace("4.1 0 8", "2.2 0 8");
        let err = parse(old.as_bytes(), "old.msh").unwrap_err().to_string();
        assert!(err.contains("MSH version 2.2 is not supported"), "{err}");
    }

    #[test]
    fn refuses_truncated_files() {
        let cut = &ONE_TET[..ONE_TET.find("$EndNodes").unwrap() - 4];
        assert!(parse(cut.as_bytes(), "cut.msh").is_err());
    }
}
