"""skidbench.pipeline.sources"""
