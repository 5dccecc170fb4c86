"""Config files and command-line paths: errors name the key, the schema and validate agree."""
