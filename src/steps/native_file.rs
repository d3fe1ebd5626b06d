//! A plugin library checked by reading it, without loading it (loading runs its
//! initialisers): readable, an ELF shared object for this machine, exporting the five
//! functions of the ABI. `r2d2 validate` and `run` both do this before anything loads the
//! library, so a wrong file is named without running a byte of it.
//!
//! Only 64-bit little-endian ELF (Linux on x86-64 and AArch64) is read; on other systems, or
//! a library without section headers, the check passes and the loader's own checks remain.

pub use super::error::LibraryError;
use r2d2_plugin::symbols;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

const SHT_DYNSYM: u32 = 11;
const ET_DYN: u16 = 3;
/// Symbol tables larger than this are not read (no plugin comes near).
const MAX_TABLE: u64 = 256 << 20;

/// Ok, or what is wrong with the file.
pub fn check(path: &Path) -> Result<(), LibraryError> {
    if !cfg!(all(target_os = "linux", target_endian = "little", target_pointer_width = "64")) {
        return Ok(());
    }
    let mut file = File::open(path).map_err(LibraryError::Unreadable)?;
    let mut header = [0u8; 64];
    let got = read_up_to(&mut file, &mut header).map_err(LibraryError::Unreadable)?;
    if got < 4 || header[..4] != *b"\x7fELF" {
        return Err(LibraryError::NotElf);
    }
    if got < 64 || header[4] != 2 || header[5] != 1 {
        return Err(LibraryError::NotElf64);
    }
    let u16_at = |b: &[u8], o: usize| u16::from_le_bytes([b[o], b[o + 1]]);
    let u32_at = |b: &[u8], o: usize| u32::from_le_bytes(b[o..o + 4].try_into().expect("4 bytes"));
    let u64_at = |b: &[u8], o: usize| u64::from_le_bytes(b[o..o + 8].try_into().expect("8 bytes"));
    if u16_at(&header, 16) != ET_DYN {
        return Err(LibraryError::NotShared(u16_at(&header, 16)));
    }
    let machine = u16_at(&header, 18);
    let expected = match std::env::consts::ARCH {
        "x86_64" => Some(62),
        "aarch64" => Some(183),
        _ => None,
    };
    if expected.is_some_and(|m| m != machine) {
        return Err(LibraryError::OtherMachine { machine });
    }
    let (shoff, shentsize, shnum) = (u64_at(&header, 0x28), u16_at(&header, 0x3a) as u64, u16_at(&header, 0x3c) as u64);
    if shoff == 0 || shnum == 0 || shentsize < 64 {
        return Ok(()); // no section headers (stripped hard): the loader checks the symbols
    }
    let damaged = LibraryError::Damaged;
    let sections = read_at(&mut file, shoff, shentsize * shnum).map_err(|_| damaged("its section headers lie outside the file"))?;
    let section = |i: u64| &sections[(i * shentsize) as usize..(i * shentsize) as usize + 64];
    let Some(dynsym) = (0..shnum).map(section).find(|s| u32_at(s, 4) == SHT_DYNSYM) else {
        return Err(LibraryError::NoSymbols);
    };
    let strtab_index = u32_at(dynsym, 0x28) as u64;
    if strtab_index >= shnum {
        return Err(damaged("its symbol table names no string table"));
    }
    let strtab = section(strtab_index);
    let table = |s: &[u8]| (u64_at(s, 0x18), u64_at(s, 0x20));
    let ((sym_offset, sym_size), (str_offset, str_size)) = (table(dynsym), table(strtab));
    if sym_size > MAX_TABLE || str_size > MAX_TABLE {
        return Err(damaged("a symbol table larger than 256 MiB"));
    }
    let symbols_bytes = read_at(&mut file, sym_offset, sym_size).map_err(|_| damaged("its symbol table lies outside the file"))?;
    let names = read_at(&mut file, str_offset, str_size).map_err(|_| damaged("its string table lies outside the file"))?;
    // Defined (section index not 0) global or weak functions.
    let exported: Vec<&[u8]> = symbols_bytes
        .chunks_exact(24)
        .filter(|s| u16_at(s, 6) != 0 && s[4] & 0xf == 2 && matches!(s[4] >> 4, 1 | 2))
        .filter_map(|s| {
            let start = u32_at(s, 0) as usize;
            let rest = names.get(start..)?;
            Some(&rest[..rest.iter().position(|&b| b == 0)?])
        })
        .collect();
    let name = |s: &[u8]| String::from_utf8_lossy(&s[..s.len() - 1]).into_owned();
    let has = |s: &[u8]| exported.contains(&&s[..s.len() - 1]);
    if !has(symbols::ABI_VERSION) {
        return Err(LibraryError::NotAPlugin(name(symbols::ABI_VERSION)));
    }
    for s in [symbols::CREATE, symbols::STEP, symbols::LAST_ERROR, symbols::DESTROY] {
        if !has(s) {
            return Err(LibraryError::MissingSymbol(name(s)));
        }
    }
    Ok(())
}

fn read_up_to(file: &mut File, buffer: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buffer.len() {
        match file.read(&mut buffer[got..])? {
            0 => break,
            n => got += n,
        }
    }
    Ok(got)
}

/// `len` bytes at `offset`, or an error if the file is shorter.
fn read_at(file: &mut File, offset: u64, len: u64) -> std::io::Result<Vec<u8>> {
    let end = offset.checked_add(len).ok_or(std::io::ErrorKind::InvalidData)?;
    if end > file.metadata()?.len() {
        return Err(std::io::ErrorKind::UnexpectedEof.into());
    }
    file.seek(SeekFrom::Start(offset))?;
    let mut bytes = vec![0u8; len as usize];
    file.read_exact(&mut bytes)?;
    Ok(bytes)
}
