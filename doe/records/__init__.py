"""Stage files: one module per file, each with its typed record, one reader and one writer.

Every stage reads another stage's file only through these modules (CONVENTIONS.md
defines the formats).
"""
