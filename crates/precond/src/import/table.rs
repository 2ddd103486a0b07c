//! Logged data as a stream of rows: CSV (every column a scalar) and Parquet (a column may also
//! be a list of numbers, as LeRobot stores `observation.state` and `action`). Neither is read
//! whole: CSV record by record, Parquet one row group at a time and only the columns asked for.

use anyhow::{Context, bail};
use parquet::file::reader::{FileReader, SerializedFileReader};
use parquet::record::Field;
use parquet::record::reader::RowIter;
use parquet::schema::types::Type;
use std::fs::File;
use std::io::BufReader;
use std::path::Path;

/// One cell of a row.
#[derive(Debug, Clone, PartialEq)]
pub enum Cell {
    /// A number (CSV: a field that parses as one).
    Number(f64),
    /// A list of numbers (Parquet list columns).
    List(Vec<f64>),
    /// Text (CSV: a field that is no number; Parquet strings).
    Text(String),
    /// Nothing (an empty CSV field, a Parquet null).
    Missing,
}

impl Cell {
    /// What the cell holds, for error messages.
    pub fn describe(&self) -> String {
        match self {
            Self::Number(x) => x.to_string(),
            Self::List(v) => format!("a list of {} numbers", v.len()),
            Self::Text(t) => format!("{t:?}"),
            Self::Missing => "nothing".into(),
        }
    }
}

/// A column of a table: its name and whether it holds lists.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Column {
    /// The column's name as the file spells it.
    pub name: String,
    /// A list column (Parquet `LIST` of numbers).
    pub list: bool,
}

/// The formats an import reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// From the file's extension (`.parquet`/`.pq` is Parquet, anything else CSV).
    Auto,
    /// Comma-separated values with a header row.
    Csv,
    /// Apache Parquet.
    Parquet,
}

impl Format {
    /// The format of `path` (resolving `Auto` from its extension).
    pub fn of(self, path: &Path) -> Self {
        match self {
            Self::Auto => match path.extension().and_then(|e| e.to_str()) {
                Some(e) if e.eq_ignore_ascii_case("parquet") || e.eq_ignore_ascii_case("pq") => {
                    Self::Parquet
                }
                _ => Self::Csv,
            },
            other => other,
        }
    }
}

/// A file's columns and, when its metadata says (Parquet), its number of rows.
pub fn columns(path: &Path, format: Format) -> anyhow::Result<(Vec<Column>, Option<u64>)> {
    match format.of(path) {
        Format::Parquet => {
            let reader = parquet_reader(path)?;
            let meta = reader.metadata().file_metadata();
            let columns = meta
                .schema_descr()
                .root_schema()
                .get_fields()
                .iter()
                .map(|f| Column {
                    name: f.name().to_string(),
                    list: is_list(f),
                })
                .collect();
            Ok((columns, u64::try_from(meta.num_rows()).ok()))
        }
        _ => {
            let mut reader = csv_reader(path)?;
            let columns = reader
                .headers()
                .context("reading the header row")?
                .iter()
                .map(|name| Column {
                    name: name.to_string(),
                    list: false,
                })
                .collect();
            Ok((columns, None))
        }
    }
}

/// Calls `row` with the cells at `wanted` (indices into [`columns`]) of every row of the file,
/// in file order; stops at the first error (`row`'s or the file's), which names the row.
pub fn for_each_row(
    path: &Path,
    format: Format,
    wanted: &[usize],
    mut row: impl FnMut(Vec<Cell>) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    match format.of(path) {
        Format::Parquet => {
            let reader = parquet_reader(path)?;
            let root = reader
                .metadata()
                .file_metadata()
                .schema_descr()
                .root_schema();
            let fields = root.get_fields();
            let mut projected: Vec<usize> = wanted.to_vec();
            projected.sort_unstable();
            projected.dedup();
            let at: Vec<usize> = wanted
                .iter()
                .map(|w| projected.iter().position(|p| p == w).unwrap_or_default())
                .collect();
            let projection = Type::group_type_builder(root.name())
                .with_fields(projected.iter().map(|&i| fields[i].clone()).collect())
                .build()
                .context("projecting the Parquet schema")?;
            let mut n = 0u64;
            for g in 0..reader.num_row_groups() {
                let group = reader
                    .get_row_group(g)
                    .with_context(|| format!("reading row group {g}"))?;
                let rows = RowIter::from_row_group(Some(projection.clone()), &*group)
                    .with_context(|| format!("reading row group {g}"))?;
                for r in rows {
                    n += 1;
                    let r = r.with_context(|| format!("row {n}"))?;
                    let fields: Vec<&Field> = r.get_column_iter().map(|(_, f)| f).collect();
                    let cells = at
                        .iter()
                        .map(|&k| {
                            let field = fields.get(k).with_context(|| {
                                format!("{} columns read, column {k} asked", fields.len())
                            })?;
                            parquet_cell(field)
                        })
                        .collect::<anyhow::Result<Vec<_>>>()
                        .with_context(|| format!("row {n}"))?;
                    row(cells).with_context(|| format!("row {n}"))?;
                }
            }
            Ok(())
        }
        _ => {
            let mut reader = csv_reader(path)?;
            let n_columns = reader.headers()?.len();
            let mut record = csv::StringRecord::new();
            // Row numbers as an editor shows them: the header is line 1.
            let mut line = 1u64;
            while reader
                .read_record(&mut record)
                .with_context(|| format!("line {}", line + 1))?
            {
                line += 1;
                if record.len() != n_columns {
                    bail!(
                        "line {line}: {} fields for {n_columns} columns",
                        record.len()
                    );
                }
                let cells = wanted.iter().map(|&i| csv_cell(&record[i])).collect();
                row(cells).with_context(|| format!("line {line}"))?;
            }
            Ok(())
        }
    }
}

fn csv_reader(path: &Path) -> anyhow::Result<csv::Reader<BufReader<File>>> {
    let file = File::open(path).context("opening the file")?;
    Ok(csv::ReaderBuilder::new()
        .has_headers(true)
        .flexible(true)
        .trim(csv::Trim::All)
        .from_reader(BufReader::with_capacity(1 << 20, file)))
}

fn parquet_reader(path: &Path) -> anyhow::Result<SerializedFileReader<File>> {
    let file = File::open(path).context("opening the file")?;
    SerializedFileReader::new(file).context("not a readable Parquet file")
}

fn csv_cell(field: &str) -> Cell {
    if field.is_empty() {
        return Cell::Missing;
    }
    match field.parse::<f64>() {
        Ok(x) => Cell::Number(x),
        Err(_) => Cell::Text(field.to_string()),
    }
}

/// A Parquet value as a number, when it is one.
fn number(field: &Field) -> Option<f64> {
    Some(match field {
        Field::Bool(b) => f64::from(u8::from(*b)),
        Field::Byte(x) => f64::from(*x),
        Field::Short(x) => f64::from(*x),
        Field::Int(x) => f64::from(*x),
        Field::Long(x) => *x as f64,
        Field::UByte(x) => f64::from(*x),
        Field::UShort(x) => f64::from(*x),
        Field::UInt(x) => f64::from(*x),
        Field::ULong(x) => *x as f64,
        Field::Float16(x) => f64::from(*x),
        Field::Float(x) => f64::from(*x),
        Field::Double(x) => *x,
        _ => return None,
    })
}

fn parquet_cell(field: &Field) -> anyhow::Result<Cell> {
    if let Some(x) = number(field) {
        return Ok(Cell::Number(x));
    }
    Ok(match field {
        Field::Null => Cell::Missing,
        Field::Str(s) => Cell::Text(s.clone()),
        Field::ListInternal(list) => Cell::List(
            list.elements()
                .iter()
                .map(|e| number(e).with_context(|| format!("a list element {e} is not a number")))
                .collect::<anyhow::Result<_>>()?,
        ),
        other => bail!("a value {other} is neither a number, a list of numbers nor text"),
    })
}

/// Whether a Parquet field is a list (a repeated field, or a group annotated `LIST`).
fn is_list(t: &Type) -> bool {
    use parquet::basic::{ConvertedType, LogicalType, Repetition};
    let info = t.get_basic_info();
    (info.has_repetition() && info.repetition() == Repetition::REPEATED)
        || info.converted_type() == ConvertedType::LIST
        || matches!(info.logical_type_ref(), Some(LogicalType::List))
}
