"""How a report draws what report.analysis computed: terminal tables, Markdown pages, the HTML file, plots,
captions, JSON and CSV."""
