//! A structural hash of anything `serde` can serialize: each value of the serde data model
//! is fed to blake3 in a binary, prefix-free form (a tag for each `Option` and enum variant,
//! a length before each string, byte string, sequence and map, floats by their bits), so two
//! values of one type hash alike exactly when they serialize alike.
//!
//! naga's IR serializes every field but its source spans (`Arena`s and `Block`s skip them):
//! the hash of a module is the hash of its structure, wherever its code stood in the text.

use serde::ser::{self, Serialize};

/// blake3 of `value`'s serialization (see the module's documentation).
pub fn hash<T: Serialize + ?Sized>(prefix: &[u8], value: &T) -> blake3::Hash {
    let mut sink = Sink { hasher: blake3::Hasher::new(), buffer: Vec::with_capacity(BATCH) };
    sink.bytes(prefix);
    // Serializing into a hasher cannot fail: every value of the data model has a form.
    let _ = value.serialize(&mut sink);
    sink.hasher.update(&sink.buffer);
    sink.hasher.finalize()
}

/// How much is gathered before hashing it: serialization writes many small pieces.
const BATCH: usize = 32 << 10;

struct Sink {
    hasher: blake3::Hasher,
    buffer: Vec<u8>,
}

impl Sink {
    fn raw(&mut self, bytes: &[u8]) {
        self.buffer.extend_from_slice(bytes);
        if self.buffer.len() >= BATCH {
            self.hasher.update(&self.buffer);
            self.buffer.clear();
        }
    }

    fn len(&mut self, n: usize) {
        self.raw(&(n as u64).to_le_bytes());
    }

    fn bytes(&mut self, b: &[u8]) {
        self.len(b.len());
        self.raw(b);
    }
}

#[derive(Debug)]
pub struct Never;

impl std::fmt::Display for Never {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("unreachable")
    }
}

impl std::error::Error for Never {}

impl ser::Error for Never {
    fn custom<T: std::fmt::Display>(_: T) -> Self {
        Never
    }
}

/// Tags of the forms that could otherwise read alike.
const NONE: u8 = 0;
const SOME: u8 = 1;
/// Before each element of a sequence or map whose length is not known up front, and at its end.
const MORE: u8 = 1;
const END: u8 = 0;

impl<'a> ser::Serializer for &'a mut Sink {
    type Ok = ();
    type Error = Never;
    type SerializeSeq = Compound<'a>;
    type SerializeTuple = Compound<'a>;
    type SerializeTupleStruct = Compound<'a>;
    type SerializeTupleVariant = Compound<'a>;
    type SerializeMap = Compound<'a>;
    type SerializeStruct = Compound<'a>;
    type SerializeStructVariant = Compound<'a>;

    fn serialize_bool(self, v: bool) -> Result<(), Never> {
        self.raw(&[v as u8]);
        Ok(())
    }
    fn serialize_i8(self, v: i8) -> Result<(), Never> {
        self.raw(&v.to_le_bytes());
        Ok(())
    }
    fn serialize_i16(self, v: i16) -> Result<(), Never> {
        self.raw(&v.to_le_bytes());
        Ok(())
    }
    fn serialize_i32(self, v: i32) -> Result<(), Never> {
        self.raw(&v.to_le_bytes());
        Ok(())
    }
    fn serialize_i64(self, v: i64) -> Result<(), Never> {
        self.raw(&v.to_le_bytes());
        Ok(())
    }
    fn serialize_i128(self, v: i128) -> Result<(), Never> {
        self.raw(&v.to_le_bytes());
        Ok(())
    }
    fn serialize_u8(self, v: u8) -> Result<(), Never> {
        self.raw(&[v]);
        Ok(())
    }
    fn serialize_u16(self, v: u16) -> Result<(), Never> {
        self.raw(&v.to_le_bytes());
        Ok(())
    }
    fn serialize_u32(self, v: u32) -> Result<(), Never> {
        self.raw(&v.to_le_bytes());
        Ok(())
    }
    fn serialize_u64(self, v: u64) -> Result<(), Never> {
        self.raw(&v.to_le_bytes());
        Ok(())
    }
    fn serialize_u128(self, v: u128) -> Result<(), Never> {
        self.raw(&v.to_le_bytes());
        Ok(())
    }
    fn serialize_f32(self, v: f32) -> Result<(), Never> {
        self.raw(&v.to_bits().to_le_bytes());
        Ok(())
    }
    fn serialize_f64(self, v: f64) -> Result<(), Never> {
        self.raw(&v.to_bits().to_le_bytes());
        Ok(())
    }
    fn serialize_char(self, v: char) -> Result<(), Never> {
        self.raw(&(v as u32).to_le_bytes());
        Ok(())
    }
    fn serialize_str(self, v: &str) -> Result<(), Never> {
        self.bytes(v.as_bytes());
        Ok(())
    }
    fn serialize_bytes(self, v: &[u8]) -> Result<(), Never> {
        self.bytes(v);
        Ok(())
    }
    fn serialize_none(self) -> Result<(), Never> {
        self.raw(&[NONE]);
        Ok(())
    }
    fn serialize_some<T: Serialize + ?Sized>(self, value: &T) -> Result<(), Never> {
        self.raw(&[SOME]);
        value.serialize(self)
    }
    fn serialize_unit(self) -> Result<(), Never> {
        Ok(())
    }
    fn serialize_unit_struct(self, _: &'static str) -> Result<(), Never> {
        Ok(())
    }
    fn serialize_unit_variant(self, _: &'static str, index: u32, _: &'static str) -> Result<(), Never> {
        self.serialize_u32(index)
    }
    fn serialize_newtype_struct<T: Serialize + ?Sized>(self, _: &'static str, value: &T) -> Result<(), Never> {
        value.serialize(self)
    }
    fn serialize_newtype_variant<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        index: u32,
        _: &'static str,
        value: &T,
    ) -> Result<(), Never> {
        self.raw(&index.to_le_bytes());
        value.serialize(self)
    }
    fn serialize_seq(self, len: Option<usize>) -> Result<Compound<'a>, Never> {
        Ok(Compound::open(self, len))
    }
    fn serialize_tuple(self, _: usize) -> Result<Compound<'a>, Never> {
        Ok(Compound { sink: self, unsized_: false })
    }
    fn serialize_tuple_struct(self, _: &'static str, _: usize) -> Result<Compound<'a>, Never> {
        Ok(Compound { sink: self, unsized_: false })
    }
    fn serialize_tuple_variant(
        self,
        _: &'static str,
        index: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Compound<'a>, Never> {
        self.raw(&index.to_le_bytes());
        Ok(Compound { sink: self, unsized_: false })
    }
    fn serialize_map(self, len: Option<usize>) -> Result<Compound<'a>, Never> {
        Ok(Compound::open(self, len))
    }
    fn serialize_struct(self, _: &'static str, _: usize) -> Result<Compound<'a>, Never> {
        Ok(Compound { sink: self, unsized_: false })
    }
    fn serialize_struct_variant(
        self,
        _: &'static str,
        index: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Compound<'a>, Never> {
        self.raw(&index.to_le_bytes());
        Ok(Compound { sink: self, unsized_: false })
    }
}

/// A sequence, tuple, map or struct being serialized. Structs and tuples have a fixed shape
/// for their type; a sequence or map is prefixed by its length, or, when that is not known
/// up front, each element by [`MORE`] and the whole ended by [`END`]. A struct's skipped
/// field is the same for every value of the type, so it needs no mark.
pub struct Compound<'a> {
    sink: &'a mut Sink,
    unsized_: bool,
}

impl<'a> Compound<'a> {
    fn open(sink: &'a mut Sink, len: Option<usize>) -> Self {
        match len {
            Some(n) => {
                sink.len(n);
                Compound { sink, unsized_: false }
            }
            None => Compound { sink, unsized_: true },
        }
    }

    fn element<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Never> {
        if self.unsized_ {
            self.sink.raw(&[MORE]);
        }
        value.serialize(&mut *self.sink)
    }

    fn close(self) -> Result<(), Never> {
        if self.unsized_ {
            self.sink.raw(&[END]);
        }
        Ok(())
    }
}

impl ser::SerializeSeq for Compound<'_> {
    type Ok = ();
    type Error = Never;
    fn serialize_element<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Never> {
        self.element(value)
    }
    fn end(self) -> Result<(), Never> {
        self.close()
    }
}

impl ser::SerializeTuple for Compound<'_> {
    type Ok = ();
    type Error = Never;
    fn serialize_element<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Never> {
        self.element(value)
    }
    fn end(self) -> Result<(), Never> {
        self.close()
    }
}

impl ser::SerializeTupleStruct for Compound<'_> {
    type Ok = ();
    type Error = Never;
    fn serialize_field<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Never> {
        self.element(value)
    }
    fn end(self) -> Result<(), Never> {
        self.close()
    }
}

impl ser::SerializeTupleVariant for Compound<'_> {
    type Ok = ();
    type Error = Never;
    fn serialize_field<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Never> {
        self.element(value)
    }
    fn end(self) -> Result<(), Never> {
        self.close()
    }
}

impl ser::SerializeMap for Compound<'_> {
    type Ok = ();
    type Error = Never;
    fn serialize_key<T: Serialize + ?Sized>(&mut self, key: &T) -> Result<(), Never> {
        self.element(key)
    }
    fn serialize_value<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Never> {
        value.serialize(&mut *self.sink)
    }
    fn end(self) -> Result<(), Never> {
        self.close()
    }
}

impl ser::SerializeStruct for Compound<'_> {
    type Ok = ();
    type Error = Never;
    fn serialize_field<T: Serialize + ?Sized>(&mut self, _: &'static str, value: &T) -> Result<(), Never> {
        self.element(value)
    }
    fn end(self) -> Result<(), Never> {
        self.close()
    }
}

impl ser::SerializeStructVariant for Compound<'_> {
    type Ok = ();
    type Error = Never;
    fn serialize_field<T: Serialize + ?Sized>(&mut self, _: &'static str, value: &T) -> Result<(), Never> {
        self.element(value)
    }
    fn end(self) -> Result<(), Never> {
        self.close()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(serde::Serialize)]
    enum E {
        A,
        B(u8),
        C { x: Option<u8>, y: Vec<String> },
    }

    #[test]
    fn values_that_differ_hash_differently() {
        let values = [
            E::A,
            E::B(0),
            E::B(1),
            E::C { x: None, y: vec![] },
            E::C { x: Some(0), y: vec![] },
            E::C { x: None, y: vec!["".into()] },
            E::C { x: None, y: vec!["a".into(), "b".into()] },
            E::C { x: None, y: vec!["ab".into()] },
            E::C { x: None, y: vec!["a".into(), "".into(), "b".into()] },
        ];
        let hashes: std::collections::HashSet<blake3::Hash> = values.iter().map(|v| hash(b"t", v)).collect();
        assert_eq!(hashes.len(), values.len());
        assert_eq!(hash(b"t", &E::B(1)), hash(b"t", &E::B(1)));
        assert_ne!(hash(b"t", &E::B(1)), hash(b"u", &E::B(1)));
        assert_ne!(hash(b"t", &0.0f32), hash(b"t", &-0.0f32));
    }
}
