//! Writes ONNX model files (the `onnx.proto` protobuf schema, IR version 8,
//! default operator set) from a graph described in Rust.
//!
//! Used to export the gripper U-Net so other tools can run it, and by the
//! tests to make the tiny models that exercise the learned backends (no
//! weights can be downloaded here). The encoder is a few dozen lines of
//! protobuf wire format (varints and length-delimited fields), so no
//! protobuf crate or generated code is needed; field numbers are those of
//! `onnx/onnx.proto` and are named where they are used.

use std::collections::BTreeMap;

/// A tensor dimension of a graph input or output.
#[derive(Debug, Clone, PartialEq)]
pub enum Dim {
    Fixed(i64),
    /// A symbolic (dynamic) dimension.
    Named(String),
}

/// Element type of a graph input or output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ElementType {
    Float,
    Int64,
}

impl ElementType {
    /// `TensorProto.DataType`.
    fn code(self) -> u64 {
        match self {
            ElementType::Float => 1,
            ElementType::Int64 => 7,
        }
    }
}

/// An operator attribute.
#[derive(Debug, Clone, PartialEq)]
pub enum Attribute {
    Int(i64),
    Float(f32),
    Ints(Vec<i64>),
    Floats(Vec<f32>),
    Text(String),
}

#[derive(Debug, Clone, PartialEq)]
struct Node {
    op: String,
    inputs: Vec<String>,
    outputs: Vec<String>,
    attributes: Vec<(String, Attribute)>,
}

#[derive(Debug, Clone, PartialEq)]
enum InitialValues {
    Float(Vec<f32>),
    Int64(Vec<i64>),
}

#[derive(Debug, Clone, PartialEq)]
struct ValueInfo {
    name: String,
    element: ElementType,
    dims: Vec<Dim>,
}

/// An ONNX graph under construction.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Graph {
    name: String,
    nodes: Vec<Node>,
    initializers: Vec<(String, Vec<i64>, InitialValues)>,
    inputs: Vec<ValueInfo>,
    outputs: Vec<ValueInfo>,
    metadata: BTreeMap<String, String>,
}

impl Graph {
    pub fn new(name: &str) -> Graph {
        Graph {
            name: name.into(),
            ..Graph::default()
        }
    }

    pub fn input(&mut self, name: &str, element: ElementType, dims: Vec<Dim>) -> &mut Self {
        self.inputs.push(ValueInfo {
            name: name.into(),
            element,
            dims,
        });
        self
    }

    pub fn output(&mut self, name: &str, element: ElementType, dims: Vec<Dim>) -> &mut Self {
        self.outputs.push(ValueInfo {
            name: name.into(),
            element,
            dims,
        });
        self
    }

    /// A constant float tensor, row-major.
    pub fn constant(&mut self, name: &str, dims: &[i64], values: Vec<f32>) -> &mut Self {
        self.initializers
            .push((name.into(), dims.to_vec(), InitialValues::Float(values)));
        self
    }

    /// A constant int64 tensor (shapes, axes, indices).
    pub fn constant_int64(&mut self, name: &str, dims: &[i64], values: Vec<i64>) -> &mut Self {
        self.initializers
            .push((name.into(), dims.to_vec(), InitialValues::Int64(values)));
        self
    }

    /// An operator of the default domain. An empty input name is an omitted
    /// optional input.
    pub fn node(
        &mut self,
        op: &str,
        inputs: &[&str],
        outputs: &[&str],
        attributes: Vec<(&str, Attribute)>,
    ) -> &mut Self {
        self.nodes.push(Node {
            op: op.into(),
            inputs: inputs.iter().map(|s| s.to_string()).collect(),
            outputs: outputs.iter().map(|s| s.to_string()).collect(),
            attributes: attributes
                .into_iter()
                .map(|(k, v)| (k.to_string(), v))
                .collect(),
        });
        self
    }

    /// A `metadata_props` entry of the model.
    pub fn metadata(&mut self, key: &str, value: &str) -> &mut Self {
        self.metadata.insert(key.into(), value.into());
        self
    }

    /// The serialised `ModelProto` (operator set `opset` of the default domain).
    pub fn to_model_bytes(&self, opset: i64) -> Vec<u8> {
        let mut model = Message::default();
        model.int(1, 8); // ir_version
        model.text(2, "omniscan"); // producer_name
        model.text(3, env!("CARGO_PKG_VERSION")); // producer_version
        let mut graph = Message::default();
        for (i, node) in self.nodes.iter().enumerate() {
            let mut n = Message::default();
            for input in &node.inputs {
                n.text(1, input);
            }
            for output in &node.outputs {
                n.text(2, output);
            }
            n.text(3, &format!("{}_{i}", node.op)); // name
            n.text(4, &node.op); // op_type
            for (name, value) in &node.attributes {
                n.message(5, &attribute(name, value));
            }
            graph.message(1, &n);
        }
        graph.text(2, &self.name);
        for (name, dims, values) in &self.initializers {
            let mut t = Message::default();
            for &d in dims {
                t.int(1, d as u64);
            }
            let (code, raw) = match values {
                InitialValues::Float(v) => (
                    ElementType::Float.code(),
                    v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>(),
                ),
                InitialValues::Int64(v) => (
                    ElementType::Int64.code(),
                    v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                ),
            };
            t.int(2, code); // data_type
            t.text(8, name);
            t.bytes(9, &raw); // raw_data, little-endian
            graph.message(5, &t);
        }
        for (field, list) in [(11, &self.inputs), (12, &self.outputs)] {
            for info in list {
                graph.message(field, &value_info(info));
            }
        }
        model.message(7, &graph);
        let mut opset_id = Message::default();
        opset_id.text(1, "");
        opset_id.int(2, opset as u64);
        model.message(8, &opset_id);
        for (key, value) in &self.metadata {
            let mut entry = Message::default();
            entry.text(1, key);
            entry.text(2, value);
            model.message(14, &entry);
        }
        model.0
    }
}

fn attribute(name: &str, value: &Attribute) -> Message {
    // AttributeProto: name 1, f 2, i 3, s 4, floats 7, ints 8, type 20.
    let mut a = Message::default();
    a.text(1, name);
    let kind = match value {
        Attribute::Float(f) => {
            a.float(2, *f);
            1
        }
        Attribute::Int(i) => {
            a.int(3, *i as u64);
            2
        }
        Attribute::Text(s) => {
            a.text(4, s);
            3
        }
        Attribute::Floats(v) => {
            for &f in v {
                a.float(7, f);
            }
            6
        }
        Attribute::Ints(v) => {
            for &i in v {
                a.int(8, i as u64);
            }
            7
        }
    };
    a.int(20, kind);
    a
}

fn value_info(info: &ValueInfo) -> Message {
    // TensorShapeProto.Dimension: dim_value 1, dim_param 2.
    let mut shape = Message::default();
    for dim in &info.dims {
        let mut d = Message::default();
        match dim {
            Dim::Fixed(v) => d.int(1, *v as u64),
            Dim::Named(s) => d.text(2, s),
        }
        shape.message(1, &d);
    }
    // TypeProto.Tensor: elem_type 1, shape 2; TypeProto: tensor_type 1.
    let mut tensor = Message::default();
    tensor.int(1, info.element.code());
    tensor.message(2, &shape);
    let mut ty = Message::default();
    ty.message(1, &tensor);
    // ValueInfoProto: name 1, type 2.
    let mut v = Message::default();
    v.text(1, &info.name);
    v.message(2, &ty);
    v
}

/// Protobuf wire-format writer.
#[derive(Default)]
struct Message(Vec<u8>);

impl Message {
    fn varint(&mut self, mut v: u64) {
        loop {
            let byte = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                self.0.push(byte);
                return;
            }
            self.0.push(byte | 0x80);
        }
    }
    fn key(&mut self, field: u64, wire: u64) {
        self.varint(field << 3 | wire);
    }
    /// int32/int64/enum (negative values as ten-byte two's complement, as protobuf does).
    fn int(&mut self, field: u64, v: u64) {
        self.key(field, 0);
        self.varint(v);
    }
    fn float(&mut self, field: u64, v: f32) {
        self.key(field, 5);
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn bytes(&mut self, field: u64, v: &[u8]) {
        self.key(field, 2);
        self.varint(v.len() as u64);
        self.0.extend_from_slice(v);
    }
    fn text(&mut self, field: u64, v: &str) {
        self.bytes(field, v.as_bytes());
    }
    fn message(&mut self, field: u64, m: &Message) {
        self.bytes(field, &m.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn varints_and_negative_ints_follow_the_wire_format() {
        let mut m = Message::default();
        m.varint(300);
        assert_eq!(m.0, vec![0xac, 0x02]);
        let mut m = Message::default();
        m.int(1, -1i64 as u64);
        // Key (field 1, varint) then ten bytes of two's complement.
        assert_eq!(m.0.len(), 11);
        assert_eq!(m.0[0], 0x08);
        assert_eq!(*m.0.last().unwrap(), 0x01);
    }
}
