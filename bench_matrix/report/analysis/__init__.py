"""What a report computes from stored records: pure functions and values (no rich, no matplotlib, no Markdown
or HTML); report.render draws them."""
